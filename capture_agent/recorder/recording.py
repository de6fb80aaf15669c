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

Writing happens on the recording's writer thread (``capture_agent/recorder/write_queue.py``):
the I/O thread only queues frames, gap records, sets, flushes and the close, so a stalling disk
never
stops it. While the queue (``write_queue_bytes``) is full, frames are refused and counted per
camera in ``not_written_disk_stalled``; the synchroniser sees only the frames queued, and the
writer thread maps the sets' frames to file rows (a frame it could not write is a missing member).

Write failures (disk full, I/O error): the session writer keeps what it could not write and
retries it at every flush; while it fails, it refuses new frames, which are counted per camera in
``not_written_write_failed``. ``write_failing_s`` says for how long; the recorder stops the
take when that grows too long. Whatever happens, ``finish`` returns a summary; a file whose disk
does not answer within the stop's budget is closed by the writer thread when it does.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from capture_agent.recorder.accounting import StreamAccounting
from capture_agent.recorder.events import EventLimiter, EventRow
from capture_agent.recorder.sync import SyncedSet, Synchroniser
from capture_agent.recorder.write_queue import WriteQueue
from protocol.session import EventKind, SessionWriteError, SessionWriter
from protocol.wire import FrameMessage

log = logging.getLogger(__name__)

TAKE_START_WAIT_NS = 2_000_000_000  # a take starts on a partial set after this long
DEFAULT_WRITE_QUEUE_BYTES = 256_000_000  # rig.toml's write_queue_mb default
FINISH_WRITE_S = 3.0  # finish() waits this long for the queued frames to be written...
FINISH_CLOSE_S = 1.0  # ...then this long for the file to close
# the disk check averages the write rate over at least this long: a burst of the first seconds
# (bounded by the cameras' caps) must not read as the take's rate
RATE_WINDOW_MIN_S = 30.0


@dataclass
class Recording:
    writer: SessionWriter  # used by the writer thread only, once the recording exists
    sync: Synchroniser
    accounting: StreamAccounting
    case: str
    started_unix_ns: int
    started_monotonic: float
    serials: tuple[int, ...]
    write_queue_bytes: int = DEFAULT_WRITE_QUEUE_BYTES
    # the cameras' configured rate x their typical frame (``CameraTable.planned_byte_rate``)
    planned_bytes_per_s: float = 0.0
    leading_sets_skipped: int = 0
    trailing_sets_skipped: int = 0
    take_started: bool = False
    ignored_frames: int = 0
    last_flush: float = 0.0  # when the last flush was queued (monotonic)
    # set by begin_stop: frames captured after stop_unix_ns are not part of the take
    stop_unix_ns: int | None = None
    stop_began_monotonic: float | None = None
    write_to_stop: bool = True  # False: frames of the take still arriving are only counted
    passed_stop: set[int] = field(default_factory=set)
    not_written_at_stop: collections.Counter[int] = field(default_factory=collections.Counter)
    # frames refused because the write queue was full (the disk stalled or fell behind)
    not_written_disk_stalled: collections.Counter[int] = field(default_factory=collections.Counter)
    # session events (``append_event``), aggregated under a flood; every occurrence per kind
    events: EventLimiter = field(default_factory=EventLimiter)
    event_counts: collections.Counter[str] = field(default_factory=collections.Counter)
    queue: WriteQueue = field(init=False)

    def __post_init__(self) -> None:
        self.queue = WriteQueue(self.writer, self.write_queue_bytes)

    # -- what the writer thread counts (read-only here) ----------------------------------------
    @property
    def frames_written(self) -> int:
        return sum(self.queue.frames_written.values())

    @property
    def sets_written(self) -> int:
        return self.queue.sets_written

    @property
    def bytes_written(self) -> int:
        return self.queue.bytes_written

    @property
    def not_written_write_failed(self) -> collections.Counter[int]:
        return self.queue.not_written_write_failed

    @property
    def write_failing_since(self) -> float | None:
        return self.queue.write_failing_since

    @property
    def write_error(self) -> str:
        return self.queue.write_error

    # -- frames ------------------------------------------------------------------------------
    def write_frame(self, msg: FrameMessage, recorder_receive_unix_ns: int) -> None:
        """Queue one received frame (of any camera) for the file, as the take and the stop
        decide; never waits for the disk."""
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
            self.queue.put_gap(
                gap.camera_serial,
                kind=int(gap.kind),
                first_missing_frame_index=gap.first_missing_frame_index,
                missing_count=gap.missing_count,
                start_unix_ns=gap.start_unix_ns,
                end_unix_ns=gap.end_unix_ns,
            )
        for kind, node_id, camera_serial, detail in self.accounting.take_notes():
            self.append_event(kind, node_id, camera_serial, detail)
        ticket = self.queue.put_frame(msg, recorder_receive_unix_ns)
        if ticket is None:
            self.not_written_disk_stalled[serial] += 1
            n = sum(self.not_written_disk_stalled.values())
            if n == 1 or n % 1000 == 0:
                log.error(
                    "case %s: the write queue is full (%.0f MB; the writer has been in one call "
                    "for %.1f s): %d frames refused so far; check the disk holding %s",
                    self.case,
                    self.queue.queued_bytes / 1e6,
                    self.queue.stalled_s(),
                    n,
                    self.writer.path.parent,
                )
            return
        self._write_sets(
            self.sync.add(serial, msg.capture_unix_ns, ticket, recorder_receive_unix_ns)
        )

    def poll(self, now_unix_ns: int) -> None:
        """Queue the sets that time (a silent camera's timeout) completes, and the session
        events held for an aggregate whose window ended."""
        self._write_sets(self.sync.poll(now_unix_ns))
        self._put_events(self.events.due(now_s=time.monotonic(), now_ns=now_unix_ns))

    # -- session events ----------------------------------------------------------------------
    def append_event(
        self, kind: EventKind, node_id: str, camera_serial: int = -1, detail: str = ""
    ) -> None:
        """Record a session event (``/events``) in the take's file, in order with what was
        queued before it; never waits. ``camera_serial`` -1 for an event of the node as a
        whole. A flood of one kind from one node is written as counted aggregates
        (``capture_agent/recorder/events.py``), so it cannot fill the file."""
        kind = EventKind(kind)
        self.event_counts[kind.name.lower()] += 1
        now_s, now_ns = time.monotonic(), time.time_ns()
        self._put_events(
            self.events.admit(kind, node_id, camera_serial, detail, now_s=now_s, now_ns=now_ns)
        )

    def refused_frame(self, msg: FrameMessage, why: EventKind, detail: str) -> None:
        """A frame of a take's camera the camera table refused (``why``): a session event, and
        the accounting's, so the frame is counted as refused, not as a drop or a loss."""
        if msg.camera_serial not in self.serials:
            return
        if self.stop_unix_ns is not None and msg.capture_unix_ns > self.stop_unix_ns:
            return  # not part of the take
        self.accounting.refused(msg.camera_serial, msg.seq, msg.node_id)
        self.append_event(why, msg.node_id, msg.camera_serial, detail)

    def _put_events(self, rows: list[EventRow]) -> None:
        for row in rows:
            self.queue.put_event(
                int(row.kind),
                time_unix_ns=row.time_unix_ns,
                node_id=row.node_id,
                camera_serial=row.camera_serial,
                count=row.count,
                detail=row.detail,
            )

    def request_flush(self) -> None:
        """Queue a flush (never waits): what was queued before it becomes durable."""
        self.last_flush = time.monotonic()
        self.queue.request_flush()

    def flush(self, timeout_s: float = 30.0) -> None:
        """Queue a flush and wait for it (tests, tools): raises ``SessionWriteError`` while
        writes fail, ``TimeoutError`` when the disk does not answer within ``timeout_s``."""
        self.request_flush()
        if not self.queue.wait_idle(timeout_s):
            raise TimeoutError(f"{self.writer.path}: the disk did not answer in {timeout_s:g} s")
        if self.write_failing_since is not None:
            raise SessionWriteError(self.write_error)

    def wait_written(self, timeout_s: float) -> bool:
        """Wait until everything queued is done; False if it took longer than ``timeout_s``."""
        return self.queue.wait_idle(timeout_s)

    def take_rate_bytes_per_s(self, now_monotonic: float) -> float:
        """The take's rate for the disk check: the planned rate, or the write rate over the
        take (at least ``RATE_WINDOW_MIN_S``) when a sustained rise makes that higher."""
        elapsed = max(now_monotonic - self.started_monotonic, RATE_WINDOW_MIN_S)
        return max(self.planned_bytes_per_s, self.bytes_written / elapsed)

    def write_failing_s(self) -> float:
        """For how long the session file has not been writable (0 while it is)."""
        since = self.write_failing_since
        return 0.0 if since is None else time.monotonic() - since

    def write_stalled_s(self) -> float:
        """For how long the writer has been inside one call into the file (0 under a second)."""
        return self.queue.stalled_s()

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
            self.queue.put_set(s.set_unix_ns, s.members, s.spread_ns)

    # -- the stop ----------------------------------------------------------------------------
    def begin_stop(self, stop_unix_ns: int, *, write: bool) -> None:
        self.stop_unix_ns = stop_unix_ns
        self.stop_began_monotonic = time.monotonic()
        self.write_to_stop = write

    def finish(
        self,
        reason: str,
        extra: dict[str, Any],
        *,
        write_s: float = FINISH_WRITE_S,
        close_s: float = FINISH_CLOSE_S,
        on_closed: Callable[[], None] | None = None,
    ) -> dict[str, Any]:
        """Queue the last sets, wait up to ``write_s`` (from ``begin_stop``) for the queued
        frames to be written, count those that are not as ``not_written_at_stop``, close the
        file with its summary and return the summary.

        When the file does not close within ``close_s`` more (a disk that still stalls), the
        summary so far is returned with ``closing`` set; the writer thread closes the file (and
        calls ``on_closed``) when the disk answers, with the final counts in its summary."""
        tail = self.sync.flush()
        # Likewise at the end: windows the stop cut short (some cameras' frames for them were
        # captured after the stop) are not sets of the take; a take ends on a complete set.
        while tail and any(m is None for m in tail[-1].members):
            tail.pop()
            self.trailing_sets_skipped += 1
        self._write_sets(tail)
        self._put_events(self.events.drain(now_ns=time.time_ns()))
        self.queue.request_flush()
        began = self.stop_began_monotonic or time.monotonic()
        left = began + write_s - time.monotonic()
        if not self.write_to_stop or not self.queue.wait_idle(max(left, 0.0)):
            self.queue.discard()  # the frames still queued are counted, not written
        self.queue.close(lambda: self._summary(reason, extra), on_closed)
        if self.queue.closed.wait(close_s) and self.queue.summary is not None:
            return self.queue.summary
        summary = self._summary(reason, extra, still_queued=True)
        summary["closing"] = (
            f"the disk did not answer within the stop's {write_s + close_s:g} s; the writer "
            "closes the file when it does (the file's own summary has the final counts)"
        )
        log.error("case %s: %s", self.case, summary["closing"])
        return summary

    def _summary(
        self, reason: str, extra: dict[str, Any], still_queued: bool = False
    ) -> dict[str, Any]:
        """The stop summary (stored in the file and replied to the stop). ``still_queued``:
        count the frames still in the write queue as not written at the stop (they will not
        be: the queue discards them)."""
        q = self.queue
        queued = collections.Counter(q.queued_frames) if still_queued else collections.Counter()
        at_stop = self.not_written_at_stop + q.not_written_at_stop + queued
        stopped_ns = time.time_ns()
        totals = self.accounting.totals()
        per_camera = {}
        for s in self.serials:
            t = totals.get(s)
            per_camera[str(s)] = {
                "frames": int(q.frames_written[s]),
                "dropped": t.frames_dropped_camera if t else 0,
                "transport_lost": t.transport_lost if t else 0,
                "time_gaps": t.time_gaps if t else 0,
                "reconnects": t.reconnects if t else 0,
                # refused by the recorder (stamp back, over its rate or bytes): not in the file
                "refused": t.frames_refused if t else 0,
                "missing_in_sets": int(q.missing_in_sets[s]),
                "unassigned": int(self.sync.unassigned_frames.get(s, 0)),
                "not_written_at_stop": int(at_stop[s]),
                "not_written_write_failed": int(q.not_written_write_failed[s]),
                "not_written_disk_stalled": int(self.not_written_disk_stalled[s]),
            }
        summary = {
            "case": self.case,
            "file": str(self.writer.path),
            "reason": reason,
            "duration_s": round((stopped_ns - self.started_unix_ns) / 1e9, 3),
            "sets": q.sets_written,
            "sets_not_written": q.sets_not_written,
            "partial_sets_trimmed": self.leading_sets_skipped + self.trailing_sets_skipped,
            "frames": sum(q.frames_written.values()),
            "frames_not_written_at_stop": sum(at_stop.values()),
            "frames_not_written_write_failed": sum(q.not_written_write_failed.values()),
            "frames_not_written_disk_stalled": sum(self.not_written_disk_stalled.values()),
            "write_internal_errors": q.internal_errors,
            "bytes": q.bytes_written,
            "capture_to_durable_ms": q.latency_ms(),
            "events": dict(self.event_counts),
            "cameras": per_camera,
            **extra,
        }
        if q.write_error:
            summary["write_error"] = q.write_error
        return summary

    # -- numbers -----------------------------------------------------------------------------
    def latency_ms(self) -> dict[str, float | None]:
        return self.queue.latency_ms()
