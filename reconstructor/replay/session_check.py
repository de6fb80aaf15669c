"""The review commands' check that a roles, trajectory, site or field file was made for the
case's own session (``protocol/formats/session_id.py`` has the ``[session]`` table).

A case knows its session from its index (``case.json``: the session file's path and start);
the session's name is read from that file when it is still there. A file made for another
session is refused in one line naming both; a file that names no session is used, with one
warning line, since a site measured by hand or a path written by hand has none to name.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from protocol.errors import UserError
from protocol.formats.session_id import SessionId, check_made_for, session_toml_lines
from protocol.formats.site import SiteBox, read_site_file
from protocol.formats.trajectory import Trajectory, read_trajectory_file
from protocol.toml_config import load_toml, read_table
from reconstructor.case.index import INDEX_NAME, CaseIndex
from reconstructor.errors import CaseReplayError

log = logging.getLogger(__name__)
MADE_FOR_NAME = "made_for.toml"  # in a review command's --out folder
REVIEW_OUTPUT_FORMAT = "egosurg-review-output"


@dataclass(frozen=True, kw_only=True)
class ReviewOutput:
    """``made_for.toml``: which command wrote an output folder, for which case and session."""

    format: str
    format_version: int
    command: str
    case: str
    about: str = ""  # what was asked: "anaesthetist sees monitor-a", "fields drape"
    session: SessionId | None = None  # None: the case records no session


def case_session(folder: Path) -> SessionId | None:
    """The session the case at ``folder`` was reconstructed from; None for a case that
    records no start (one assembled by hand or by a test, not by ``egosurg reconstruct``)."""
    if not (folder / INDEX_NAME).is_file():
        raise CaseReplayError(
            f"{folder} is not a case folder (no {INDEX_NAME}); make one with "
            "'egosurg reconstruct SESSION.h5 --every 1s --out CASE/'"
        )
    index = CaseIndex.read(folder)
    if index.session_started_unix_ns <= 0:
        return None
    return SessionId(
        name=_session_name(Path(index.session)), started_unix_ns=index.session_started_unix_ns
    )


def _session_name(path: Path) -> str:
    """The session file's ``session_name``; "" when the file is gone or unreadable (the start,
    which the case index holds, is then the whole check)."""
    from protocol.session import SessionReader  # h5py: only when a review command runs

    if not path.is_file():
        return ""
    try:
        with SessionReader(path) as reader:
            return reader.info.session_name
    except (UserError, OSError) as exc:
        log.debug("the case's session %s: name not read (%s)", path, exc)
        return ""


class CaseInputs:
    """Reads the review files given for one case, each checked against the case's session."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.session = case_session(folder)

    def _check(self, made_for: SessionId | None, path: Path | str) -> None:
        if self.session is None:
            log.debug("%s: the case records no session; %s not checked", self.folder, path)
            return
        warning = check_made_for(
            made_for, self.session, what=str(path), case=f"the case {self.folder}"
        )
        if warning is not None:
            log.warning("%s", warning)

    def trajectories(self, path: Path | str) -> tuple[Trajectory, ...]:
        file = read_trajectory_file(path)
        self._check(file.session, path)
        return file.trajectories

    def boxes(self, path: Path | str) -> dict[str, SiteBox]:
        made_for, boxes = read_site_file(path)
        self._check(made_for, path)
        return boxes

    def review_output(self, out: Path | str, command: str) -> ReviewOutput | None:
        """Refuse a ``command --out`` folder made for another session than this case's; a
        folder without ``made_for.toml`` (written before it existed) is used with a warning."""
        record = Path(out) / MADE_FOR_NAME
        if not record.is_file():
            if self.session is not None:
                log.warning(
                    "%s has no %s: it cannot be checked against the case %s (%s); make sure "
                    "it is this case's %s output", out, MADE_FOR_NAME, self.folder,
                    self.session.describe(), command,
                )  # fmt: skip
            return None
        table, _ = load_toml(record, "the review output record", error=CaseReplayError)
        made = read_table(ReviewOutput, table, str(record), error=CaseReplayError)
        if made.format != REVIEW_OUTPUT_FORMAT or made.command != command:
            raise CaseReplayError(
                f"{out} is not the output of 'egosurg {command}' ({record} says "
                f"{made.command!r}); give the folder its --out wrote"
            )
        self._check(made.session, out)
        return made


def write_made_for(out: Path, folder: Path, command: str, about: str = "") -> None:
    """``out/made_for.toml``: ``command``'s output folder made from the case at ``folder``."""
    import tomli_w

    head = {"format": REVIEW_OUTPUT_FORMAT, "format_version": 1, "command": command,
            "case": str(folder.resolve()), "about": about}  # fmt: skip
    text = tomli_w.dumps(head) + "\n".join(session_toml_lines(case_session(folder))) + "\n"
    (out / MADE_FOR_NAME).write_text(text)
