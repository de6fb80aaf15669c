"""One recording (a take) of the recorder: its session file, synchroniser and drop accounting.

The recorder's I/O thread creates a ``Recording`` at ``start`` and hands it every frame of the
take's cameras (``write_frame``); it polls it between messages (``poll``, ``flush``) and ends it
with ``finish``, which returns the stop summary. A frame goes, in this order, through the drop
and gap accounting (gap records), the session file (its row) and the synchroniser (the sets it
completes). A take begins at its first complete set and ends on a complete set.

The stop: ``begin_stop(stop_unix_ns)`` makes the take end at that time. Frames captured before it
that are still queued are written (``write_to_stop``) or, once the recorder cannot write any more
of them (disk reserve, time), counted per camera in ``not_written_at_stop``; frames captured after
it are not part of the take, and ``passed_stop`` collects the cameras that sent one (so nothing
earlier can come from them any more).

Write failures (disk full, I/O error): the session writer keeps what it could not write and
retries it at every flush; while it fails, it refuses new frames, which are counted per camera in
``not_written_write_failed``. ``write_failing_s`` says for how long; the recorder stops the
take when that grows too long. Whatever happens, ``finish`` returns a summary.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capture_agent.accounting import StreamAccounting
from capture_agent.sync import SyncedSet, Synchroniser
from protocol.messages import FrameMessage
from protocol.session import SessionWriteError, SessionWriter
from protocol.set_counts import missing_in_sets

log = logging.getLogger(__name__)

TAKE_START_WAIT_NS = 2_000_000_000  # a take starts on a partial set after this long


@dataclass
class Recording:
    writer: SessionWriter
    sync: Synchroniser
    accounting: StreamAccounting
    case: str
    started_unix_ns: int
    started_monotonic: float
    serials: tuple[int, ...]
    sets_written: int = 0
    leading_sets_skipped: int = 0
    trailing_sets_skipped: int = 0
    take_started: bool = False
    frames_written: int = 0
    ignored_frames: int = 0
    last_flush: float = 0.0
    # set by begin_stop: frames captured after stop_unix_ns are not part of the take
    stop_unix_ns: int | None = None
    write_to_stop: bool = True  # False: frames of the take still arriving are only counted
    passed_stop: set[int] = field(default_factory=set)
    not_written_at_stop: collections.Counter[int] = field(default_factory=collections.Counter)
    # frames the session writer refused while its writes failed, and since when they fail
    not_written_write_failed: collections.Counter[int] = field(default_factory=collections.Counter)
    write_failing_since: float | None = None
    # per camera, the written sets without a frame of it (the stop summary's missing_in_sets)
    missing_in_sets: collections.Counter[int] = field(default_factory=collections.Counter)
    write_error: str = ""
    # capture stamps of frames written since the last flush, and capture-to-durable latencies
    unflushed_capture_ns: list[int] = field(default_factory=list)
    durable_latency_ns: collections.deque = field(
        default_factory=lambda: collections.deque(maxlen=200_000)
    )

    # -- frames ------------------------------------------------------------------------------
    def write_frame(self, msg: FrameMessage, recorder_receive_unix_ns: int) -> None:
        """Store one received frame (of any camera), as the take and the stop decide."""
        serial = msg.camera_serial
        if serial not in self.serials:
            self.ignored_frames += 1
            return
        if self.stop_unix_ns is not None:  # stopping: only frames of the take count
            if msg.capture_unix_ns > self.stop_unix_ns:
                self.passed_stop.add(serial)
                return
            if not self.write_to_stop:
                self.not_written_at_stop[serial] += 1
                return
        for gap in self.accounting.observe(
            serial, msg.frame_index, msg.seq, msg.capture_unix_ns, msg.node_id
        ):
            self.writer.append_gap(
                gap.camera_serial,
                kind=int(gap.kind),
                first_missing_frame_index=gap.first_missing_frame_index,
                missing_count=gap.missing_count,
                start_unix_ns=gap.start_unix_ns,
                end_unix_ns=gap.end_unix_ns,
            )
        try:
            row = self._append(serial, msg, recorder_receive_unix_ns)
        except SessionWriteError as exc:
            self._write_failed(exc)
            self.not_written_write_failed[serial] += 1
            return
        self.frames_written += 1
        self.unflushed_capture_ns.append(msg.capture_unix_ns)
        self._write_sets(self.sync.add(serial, msg.capture_unix_ns, row, recorder_receive_unix_ns))

    def _append(self, serial: int, msg: FrameMessage, recorder_receive_unix_ns: int) -> int:
        return self.writer.append_frame(
            serial,
            left=msg.left,
            right=msg.right,
            capture_unix_ns=msg.capture_unix_ns,
            host_receive_unix_ns=msg.host_receive_unix_ns,
            recorder_receive_unix_ns=recorder_receive_unix_ns,
            frame_index=msg.frame_index,
            seq=msg.seq,
            ptp_offset_ns=msg.ptp_offset_ns,
            ptp_locked=msg.ptp_locked,
        )

    def poll(self, now_unix_ns: int) -> None:
        """Write the sets that time (a silent camera's timeout) completes."""
        self._write_sets(self.sync.poll(now_unix_ns))

    def flush(self) -> None:
        """Make what was written durable; raises ``SessionWriteError`` while writes fail (the
        next flush retries them)."""
        self.last_flush = time.monotonic()
        try:
            self.writer.flush()
        except SessionWriteError as exc:
            self._write_failed(exc)
            raise
        if self.write_failing_since is not None:
            log.warning(
                "case %s: the session file is written again after %.1f s of failures",
                self.case,
                self.write_failing_s(),
            )
            self.write_failing_since = None
        now = time.time_ns()
        self.durable_latency_ns.extend(now - c for c in self.unflushed_capture_ns)
        self.unflushed_capture_ns.clear()

    def write_failing_s(self) -> float:
        """For how long the session file has not been writable (0 while it is)."""
        if self.write_failing_since is None:
            return 0.0
        return time.monotonic() - self.write_failing_since

    def _write_failed(self, exc: SessionWriteError) -> None:
        self.write_error = str(exc)
        if self.write_failing_since is None:
            self.write_failing_since = time.monotonic()
            log.error("case %s: %s; frames are refused until it is writable again", self.case, exc)

    def _write_sets(self, sets: list[SyncedSet]) -> None:
        for s in sets:
            complete = all(m is not None for m in s.members)
            if not self.take_started:
                # The cameras free-run, so the first window after "start" may hold only some of
                # them. The take begins at the first complete set, so every take starts with all
                # cameras (their earlier frames are still stored, outside any set).
                waited = s.set_unix_ns - self.started_unix_ns > TAKE_START_WAIT_NS
                if not complete and not waited:
                    self.leading_sets_skipped += 1
                    continue
                self.take_started = True
            self.writer.append_set(s.set_unix_ns, s.member_rows(), s.spread_ns)
            self.sets_written += 1
            # counted as the file's readers count it (protocol/set_counts.py), sets written only
            self.missing_in_sets.update(missing_in_sets([s.member_rows()], self.serials))

    # -- the stop ----------------------------------------------------------------------------
    def begin_stop(self, stop_unix_ns: int, *, write: bool) -> None:
        self.stop_unix_ns = stop_unix_ns
        self.write_to_stop = write

    def finish(self, reason: str, extra: dict[str, Any]) -> dict[str, Any]:
        """Write the last sets, close the file with its summary, and return the summary."""
        tail = self.sync.flush()
        # Likewise at the end: windows the stop cut short (some cameras' frames for them were
        # captured after the stop) are not sets of the take; a take ends on a complete set.
        while tail and any(m is None for m in tail[-1].members):
            tail.pop()
            self.trailing_sets_skipped += 1
        self._write_sets(tail)
        try:
            self.flush()
        except SessionWriteError:
            pass  # the summary says so, and close() tries once more
        stopped_ns = time.time_ns()
        totals = self.accounting.totals()
        per_camera = {}
        for s in self.serials:
            t = totals.get(s)
            per_camera[str(s)] = {
                "frames": self.writer.frames_written(s),
                "dropped": t.frames_dropped_camera if t else 0,
                "transport_lost": t.transport_lost if t else 0,
                "time_gaps": t.time_gaps if t else 0,
                "reconnects": t.reconnects if t else 0,
                "missing_in_sets": int(self.missing_in_sets[s]),
                "unassigned": int(self.sync.unassigned_frames.get(s, 0)),
                "not_written_at_stop": int(self.not_written_at_stop[s]),
                "not_written_write_failed": int(self.not_written_write_failed[s]),
            }
        summary = {
            "case": self.case,
            "file": str(self.writer.path),
            "reason": reason,
            "duration_s": round((stopped_ns - self.started_unix_ns) / 1e9, 3),
            "sets": self.sets_written,
            "partial_sets_trimmed": self.leading_sets_skipped + self.trailing_sets_skipped,
            "frames": self.frames_written,
            "frames_not_written_at_stop": sum(self.not_written_at_stop.values()),
            "frames_not_written_write_failed": sum(self.not_written_write_failed.values()),
            "bytes": self.writer.bytes_written,
            "capture_to_durable_ms": self.latency_ms(),
            "cameras": per_camera,
            **extra,
        }
        if self.write_error:
            summary["write_error"] = self.write_error
        try:
            self.writer.close(stopped_ns, summary)
        except SessionWriteError as exc:
            # The file is closed without the clean mark and holds what the last good flush put
            # there; every frame after that is in the counts above or in this error.
            summary["write_error"] = str(exc)
            log.error("case %s: %s", self.case, exc)
        return summary

    # -- numbers -----------------------------------------------------------------------------
    def latency_ms(self) -> dict[str, float | None]:
        if not self.durable_latency_ns:
            return {"p50": None, "p99": None, "max": None}
        a = np.asarray(self.durable_latency_ns, dtype=np.float64) / 1e6
        return {
            "p50": round(float(np.percentile(a, 50)), 2),
            "p99": round(float(np.percentile(a, 99)), 2),
            "max": round(float(a.max()), 2),
        }
