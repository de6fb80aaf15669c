"""How a take ends and how it survives a kill (``capture_agent/recorder/recorder.py``'s I/O thread).

``TakeState`` owns the take: the recording in progress, the last stop's summary and a take a
killed recorder left to resume. At a stop, ``drain_to_stop`` receives the frames captured before
the stop that are still queued and writes them (or counts them as ``not_written_at_stop``) within
``StopLimits``, then ``TakeState.finish`` closes the take and keeps its summary. The take journal
(``capture_agent/recorder/take_journal.py``) is written at each start and removed once the
take's file is closed; a recorder killed mid-take finds it at its next start, and
``TakeState.resume_now`` says when to start the take again (as the next part of the same case:
once every expected camera streams) and with what arguments; the recorder starts it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capture_agent.recorder.intake import CameraTable
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.take_journal import TakeJournal, TakeResume
from capture_agent.recorder.take_journal import remove as remove_take_journal
from protocol.session.privacy import make_private_dir

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class StopLimits:
    """How long a stop may take: write the queued frames of the take for at most ``write_s``,
    then count what is still queued for at most ``count_s``, and stop waiting for frames after
    ``idle_s`` without a message."""

    write_s: float
    count_s: float
    idle_s: float


def drain_to_stop(
    rec: Recording,
    waiting: set[int],
    receive: Callable[[int], int],
    *,
    write: bool,
    flush_interval_s: float,
    limits: StopLimits,
) -> None:
    """Receive the take's frames still queued (captured before the stop): written while
    ``write`` and for up to ``limits.write_s``, then counted as not written for up to
    ``limits.count_s``. ``receive(timeout_ms)`` handles what arrives and says how much.
    Done when every camera of ``waiting`` (those still streaming) has sent a frame captured
    after the stop."""
    rec.begin_stop(time.time_ns(), write=write)
    t0 = time.monotonic()
    while not waiting <= rec.passed_stop:
        elapsed = time.monotonic() - t0
        if elapsed > limits.write_s + limits.count_s:
            break
        rec.write_to_stop = write and elapsed < limits.write_s
        if time.monotonic() - rec.last_flush >= flush_interval_s:
            rec.request_flush()  # a crash while draining loses no more than at other times
        if not receive(int(limits.idle_s * 1000)):
            break
    unwritten = sum(rec.not_written_at_stop.values())
    log.log(
        logging.WARNING if unwritten else logging.INFO,
        "stop: drained the queue in %.2f s; %d frames of the take not written%s",
        time.monotonic() - t0,
        unwritten,
        ""
        if waiting <= rec.passed_stop
        else f"; no frame after the stop from {sorted(waiting - rec.passed_stop)}",
    )


class TakeState:
    """The take: the recording in progress (None while idle), the last stop's summary, and a
    take a killed recorder left unfinished (``take_journal``). Changed by the I/O thread only."""

    def __init__(self, output_dir: str) -> None:
        self.output_dir = output_dir
        self.recording: Recording | None = None
        self.last_stop_summary: dict[str, Any] | None = None
        self.resume: TakeResume | None = None

    def load_resume(self) -> None:
        """At the recorder's start: the session folder owner-only, and the take to resume."""
        make_private_dir(self.output_dir)  # sessions are medical records: 0700
        self.resume = TakeResume.load(self.output_dir)

    # -- the resume: a question this part answers, the recorder acts on ------------------------
    def resume_now(self, table: CameraTable) -> dict[str, Any] | None:
        """The start arguments of the journal's take when it should start again now (no take
        running, its retry due, every expected camera streaming); else None. Never waits."""
        resume = self.resume
        if resume is None or self.recording is not None or not resume.due():
            return None
        expected = table.expected()
        if not expected or not all(table.is_streaming(s) for s in expected):
            return None
        return resume.start_args()

    def resume_refused(self, exc: Exception) -> None:
        """The resume's start was refused (retried later; ``status`` shows why)."""
        assert self.resume is not None
        self.resume.state = f"waiting: the start was refused: {exc}"
        log.warning("case %s not resumed yet (retrying): %s", self.resume.journal.case, exc)

    def resume_failed(self, exc: Exception) -> None:
        """The resume's start raised a bug (called in the ``except``: logs the traceback)."""
        assert self.resume is not None
        self.resume.state = f"waiting: the start failed: {exc}"
        log.exception("case %s not resumed yet (retrying)", self.resume.journal.case)

    def link(self, case: str) -> tuple[str, int]:
        """(previous_session_file, take_part) for a start of ``case``: a resumed take links to
        the part the killed recorder left."""
        return self.resume.link(case) if self.resume is not None else ("", 1)

    # -- start and stop -------------------------------------------------------------------------
    def started(
        self,
        rec: Recording,
        *,
        meta: dict,
        planned_min: float,
        path: Path,
        previous: str,
        part: int,
    ) -> None:
        """A take started: it is the recording now, and its journal is written."""
        self.recording = rec
        case = rec.case
        if self.resume is not None:
            self.resume.started(case, path.name)
        if previous:
            log.warning(
                "case %s resumed after the recorder was killed: part %d in %s continues %s",
                case,
                part,
                path,
                previous,
            )
        journal = TakeJournal(
            case=case,
            meta={str(k): str(v) for k, v in meta.items()},
            planned_duration_min=planned_min,
            file=path.name,
            take_part=part,
            written_unix_ns=time.time_ns(),
        )
        try:
            journal.write(self.output_dir)
        except OSError as exc:  # the take records; only a resume after a kill is lost
            log.error("cannot write the take journal in %s: %s", self.output_dir, exc)

    def finish(self, reason: str, counts: dict[str, int], limits: StopLimits) -> dict[str, Any]:
        """End the drained take with ``reason`` and the recorder's ``counts``; its summary."""
        rec = self.recording
        assert rec is not None
        output_dir, name = self.output_dir, rec.writer.path.name
        summary = rec.finish(
            reason,
            counts,
            write_s=limits.write_s,
            close_s=limits.count_s,
            # on the writer thread, once the file is closed (a stalled disk: later)
            on_closed=lambda: take_stopped(output_dir, name),
        )
        self.recording = None
        self.last_stop_summary = summary
        log.info("stopped case %s: %s", rec.case, reason)
        return summary


def take_stopped(output_dir: str, file_name: str) -> None:
    """Remove the take journal once the take's file is closed, unless a later take's
    journal replaced it meanwhile (a file closed late, after its disk stalled)."""
    try:
        journal = TakeJournal.read(output_dir)
        if journal is not None and journal.file != file_name:
            return
        remove_take_journal(output_dir)
    except OSError as exc:
        log.error("cannot remove the take journal in %s: %s", output_dir, exc)
