"""Resuming a take after the recorder was killed: a small journal beside the sessions.

When a take starts (or resumes), the recorder writes ``take-journal.json`` in its output folder:
the case, its metadata, the part's session file and part number. It is written atomically
(a temporary file, fsync, rename, fsync of the folder; mode 0600) and removed when the take
stops, whatever the reason: a stop by request, a full disk, a SIGTERM from systemd. So a
journal found at start means the recorder died in the middle of a take (SIGKILL, OOM, the
watchdog's SIGABRT, power), and the file it names holds everything up to its last flush.

``TakeResume`` is what the recorder keeps of such a journal. Once every expected camera streams
again, the recorder starts the same case again (``take.TakeState.resume_now`` says when and with
what, asked from its I/O loop, never waiting in it); the new file's ``previous_session_file``
names the earlier part and its ``take_part`` is one more. A start of the same case by an
operator does the same. It is not resumed when the earlier part's file is missing, when that
file was last written more than ``RESUME_WITHIN_S`` ago (a recorder down for long is not put
back into a case that has surely ended), or when another case is started first; each is
logged. A refused start (PTP unlocked, a full disk) is retried every ``RETRY_S`` and its reason
shown in ``status``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from protocol.durable import atomic_write_bytes, fsync_dir
from protocol.session.privacy import FILE_MODE

log = logging.getLogger(__name__)

JOURNAL_NAME = "take-journal.json"
JOURNAL_VERSION = 1
RESUME_WITHIN_S = 600.0
RETRY_S = 1.0


@dataclass(frozen=True, kw_only=True)
class TakeJournal:
    case: str
    meta: dict[str, str]
    planned_duration_min: float | None
    file: str  # the current part's session file name, in the journal's folder
    take_part: int
    written_unix_ns: int

    def write(self, directory: Path | str) -> None:
        """Replace the folder's journal with this one, atomically and durably."""
        data = json.dumps({"version": JOURNAL_VERSION, **asdict(self)}, sort_keys=True).encode()
        atomic_write_bytes(Path(directory) / JOURNAL_NAME, data, mode=FILE_MODE)

    @classmethod
    def read(cls, directory: Path | str) -> TakeJournal | None:
        """The folder's journal; None if there is none or it cannot be used (logged)."""
        path = Path(directory) / JOURNAL_NAME
        try:
            raw = json.loads(path.read_text())
            if raw.pop("version") != JOURNAL_VERSION:
                raise ValueError("unknown journal version")
            journal = cls(**raw)
            if not isinstance(journal.case, str) or not isinstance(journal.take_part, int):
                raise ValueError("bad field types")
            return journal
        except FileNotFoundError:
            return None
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
            log.error("take journal %s cannot be read (%s); no take is resumed", path, exc)
            remove(directory)
            return None


def remove(directory: Path | str) -> None:
    """Remove the folder's journal (the take stopped)."""
    path = Path(directory) / JOURNAL_NAME
    try:
        path.unlink()
    except FileNotFoundError:
        return
    fsync_dir(Path(directory))


class TakeResume:
    """A take to resume, from the journal a killed recorder left; see the module docstring."""

    def __init__(self, journal: TakeJournal, directory: Path) -> None:
        self.journal = journal
        self.directory = directory
        self.pending = True
        self.state = "waiting for every camera to stream"
        self.resumed_file = ""
        self._next_try = 0.0

    @classmethod
    def load(cls, directory: Path | str) -> TakeResume | None:
        folder = Path(directory)
        journal = TakeJournal.read(folder)
        if journal is None:
            return None
        previous = folder / journal.file
        try:
            age_s = time.time() - previous.stat().st_mtime
        except OSError:
            log.error(
                "case %s was being recorded when the recorder stopped, but its file %s is gone; "
                "it is not resumed",
                journal.case,
                previous,
            )
            remove(folder)
            return None
        if age_s > RESUME_WITHIN_S:
            log.warning(
                "case %s was being recorded when the recorder stopped, %.0f min ago; too long "
                "ago to resume it (start it again if it goes on). %s holds it up to then",
                journal.case,
                age_s / 60,
                previous,
            )
            remove(folder)
            return None
        log.warning(
            "case %s was being recorded (part %d, %s) when the recorder was killed; it resumes "
            "into a new file linked to that one as soon as every camera streams",
            journal.case,
            journal.take_part,
            previous,
        )
        return cls(journal, folder)

    def due(self) -> bool:
        """Whether to try the resume now (at most every RETRY_S)."""
        if not self.pending or time.monotonic() < self._next_try:
            return False
        self._next_try = time.monotonic() + RETRY_S
        return True

    def start_args(self) -> dict[str, Any]:
        args: dict[str, Any] = {"case": self.journal.case, "meta": dict(self.journal.meta)}
        if self.journal.planned_duration_min is not None:
            args["planned_duration_min"] = self.journal.planned_duration_min
        return args

    def link(self, case: str) -> tuple[str, int]:
        """(previous_session_file, take_part) for a start of ``case``."""
        if self.pending and case == self.journal.case:
            return self.journal.file, self.journal.take_part + 1
        return "", 1

    def started(self, case: str, file: str) -> None:
        """A take started (the link was used if it is the same case); no more resuming."""
        if not self.pending:
            return
        self.pending = False
        if case == self.journal.case:
            self.state, self.resumed_file = "resumed", file
            return
        self.state = f"not resumed: case {case} was started instead"
        log.warning(
            "the unfinished take of case %s is not resumed: case %s was started instead",
            self.journal.case,
            case,
        )

    def status(self) -> dict[str, Any]:
        return {
            "case": self.journal.case,
            "previous_session_file": self.journal.file,
            "take_part": self.journal.take_part + 1,
            "state": self.state,
            "file": self.resumed_file,
        }
