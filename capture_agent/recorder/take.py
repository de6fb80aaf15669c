"""How a take ends and how it survives a kill (``capture_agent/recorder/recorder.py``'s I/O thread).

At a stop, ``drain_to_stop`` receives the frames captured before the stop that are still queued
and writes them (or counts them as ``not_written_at_stop``) within ``StopLimits``, then
``stop_recording`` closes the take and keeps its summary. The take journal
(``capture_agent/recorder/take_journal.py``) is written at each start and removed once the
take's file is closed; a recorder killed mid-take finds it at its next start and resumes the take,
as the
next part of the same case, once every expected camera streams again."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capture_agent.control_server import Refused
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.take_journal import TakeJournal, TakeResume
from capture_agent.recorder.take_journal import remove as remove_take_journal
from protocol.session import SessionWriteError
from protocol.session.privacy import make_private_dir

if TYPE_CHECKING:
    from capture_agent.recorder.recorder import Recorder

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class StopLimits:
    """How long a stop may take: write the queued frames of the take for at most ``write_s``,
    then count what is still queued for at most ``count_s``, and stop waiting for frames after
    ``idle_s`` without a message."""

    write_s: float
    count_s: float
    idle_s: float


def drain_to_stop(recorder: Recorder, rec: Recording, write: bool, limits: StopLimits) -> None:
    """Receive the take's frames still queued (captured before the stop): written while
    ``write`` and for up to ``limits.write_s``, then counted as not written for up to
    ``limits.count_s``.
    Done when every camera still streaming has sent a frame captured after the stop."""
    rec.begin_stop(time.time_ns(), write=write)
    t0 = time.monotonic()
    waiting = {s for s in rec.serials if s in recorder.cameras and recorder.cameras[s].streaming()}
    while not waiting <= rec.passed_stop:
        elapsed = time.monotonic() - t0
        if elapsed > limits.write_s + limits.count_s:
            break
        rec.write_to_stop = write and elapsed < limits.write_s
        if time.monotonic() - rec.last_flush >= recorder.config.flush_interval_s:
            rec.request_flush()  # a crash while draining loses no more than at other times
        if not recorder.receive_published(int(limits.idle_s * 1000)):
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


def stop_recording(
    recorder: Recorder, reason: str, limits: StopLimits, *, write_queued: bool = True
) -> dict[str, Any]:
    rec = recorder.recording
    assert rec is not None
    drain_to_stop(recorder, rec, write_queued, limits)
    summary = rec.finish(
        reason,
        {
            "malformed_messages": recorder.malformed,
            "unknown_version_messages": recorder.unknown_version,
        },
        write_s=limits.write_s,
        close_s=limits.count_s,
        # on the writer thread, once the file is closed (a stalled disk: later)
        on_closed=lambda: take_stopped(recorder, rec.writer.path.name),
    )
    recorder.recording = None
    recorder.last_stop_summary = summary
    log.info("stopped case %s: %s", rec.case, reason)
    return summary


def resume_on_start(recorder: Recorder) -> None:
    make_private_dir(recorder.config.output_dir)  # sessions are medical records: 0700
    recorder._resume = TakeResume.load(recorder.config.output_dir)


def resume_take_if_due(recorder: Recorder) -> None:
    """Start the journal's take again once every expected camera streams (I/O thread)."""
    resume = recorder._resume
    if resume is None or recorder.recording is not None or not resume.due():
        return
    expected = recorder.config.expected_cameras or tuple(sorted(recorder.cameras))
    streaming = [s in recorder.cameras and recorder.cameras[s].streaming() for s in expected]
    if not expected or not all(streaming):
        return
    try:
        recorder._start_recording(resume.start_args())
    except (Refused, SessionWriteError) as exc:
        resume.state = f"waiting: the start was refused: {exc}"
        log.warning("case %s not resumed yet (retrying): %s", resume.journal.case, exc)
    except Exception as exc:  # a bug must not take the I/O loop down
        resume.state = f"waiting: the start failed: {exc}"
        log.exception("case %s not resumed yet (retrying)", resume.journal.case)


def take_started(
    recorder: Recorder,
    case: str,
    meta: dict,
    planned_min: float,
    path: Path,
    previous: str,
    part: int,
) -> None:
    if recorder._resume is not None:
        recorder._resume.started(case, path.name)
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
        journal.write(recorder.config.output_dir)
    except OSError as exc:  # the take records; only a resume after a kill is lost
        log.error("cannot write the take journal in %s: %s", recorder.config.output_dir, exc)


def take_stopped(recorder: Recorder, file_name: str) -> None:
    """Remove the take journal once the take's file is closed, unless a later take's
    journal replaced it meanwhile (a file closed late, after its disk stalled)."""
    try:
        journal = TakeJournal.read(recorder.config.output_dir)
        if journal is not None and journal.file != file_name:
            return
        remove_take_journal(recorder.config.output_dir)
    except OSError as exc:
        log.error("cannot remove the take journal in %s: %s", recorder.config.output_dir, exc)
