"""The recording's writer thread: every call into the session file, off the recorder's I/O thread.

Why. A stalling disk (a frozen or overloaded file system, a controller retrying) blocks a write
for seconds, and HDF5 and the chunk sink block with it. The recorder's I/O thread must go on
receiving frames and answering control meanwhile, so it never calls the ``SessionWriter`` during a
take: it hands frames, gap records, sets, flushes and the close to this thread through a queue
bounded in bytes (rig.toml's ``write_queue_mb``: the image bytes of the queued frames, which stay
in memory until written). A frame that does not fit is refused (``put_frame`` returns None; the
recording counts it per camera as ``not_written_disk_stalled``); everything else is small and
always queued. No camera holds more than its share of the queue (``camera_share_bytes``, the
bound over the cameras): one node's burst cannot take the room of the others' frames.
``stalled_s`` says for how long the thread has been inside one call. When the disk
answers again the queue drains and the take goes on.

Rows. A set names its frames by their rows in the file, which only this thread knows (a frame it
could not append has none). The I/O thread gives each queued frame a ticket, its place among the
camera's queued frames; the synchroniser's sets carry tickets, and this thread turns them into
rows, a frame that was not written becoming a missing member (-1). So a set never points at a
frame that is not in the file, and a set left without any member is not written
(``sets_not_written``). Jobs run in the order they were queued, so a set's frames come first.

Failures (disk full, I/O error) are the session writer's: it refuses appends until a flush gets
through; refused frames are counted (``not_written_write_failed``) and ``write_failing_since``
says since when. An unexpected exception in a job is counted (``internal_errors``) and logged,
and the thread goes on with the next job.
"""

from __future__ import annotations

import bisect
import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.os_thread import NamedThread
from protocol.session import SessionWriteError, SessionWriter
from protocol.set_counts import missing_in_sets
from protocol.wire import FrameMessage

log = logging.getLogger(__name__)

STALL_REPORT_S = 1.0  # a call into the file that lasts longer is reported as a stall
SMALL_JOB_BYTES = 256  # what a gap, set or flush job is counted at in the queue's bytes


@dataclass(frozen=True)
class _Frame:
    msg: FrameMessage
    ticket: int
    recorder_receive_unix_ns: int
    nbytes: int


@dataclass(frozen=True)
class _Gap:
    camera_serial: int
    fields: dict[str, int]


@dataclass(frozen=True)
class _Event:
    kind: int
    fields: dict[str, Any]


@dataclass(frozen=True)
class _Set:
    set_unix_ns: int
    tickets: tuple[int | None, ...]
    spread_ns: int


@dataclass(frozen=True)
class _Flush:
    pass


@dataclass(frozen=True)
class _Close:
    build_summary: Callable[[], dict[str, Any]]
    on_closed: Callable[[], None] | None


class WriteQueue:
    """A ``SessionWriter`` driven by a thread of its own; see the module docstring.

    The producer (the recorder's I/O thread) calls ``put_*``, ``request_flush``, ``discard`` and
    ``close``; everything else it reads (counters, ``stalled_s``) is written by the writer thread
    alone, so plain reads see a recent value."""

    def __init__(self, writer: SessionWriter, max_bytes: int) -> None:
        if max_bytes <= 0:
            raise ValueError(f"the write queue needs a bound > 0 bytes, got {max_bytes}")
        self.writer = writer
        self.max_bytes = max_bytes
        self.serials = writer.camera_serials
        self._cv = threading.Condition()
        self._jobs: collections.deque[Any] = collections.deque()
        self.queued_bytes = 0  # counted until a job is done: its frame's memory is held till then
        # Every per-camera count holds every camera from the start: the producer reads them
        # while this thread counts, and a dict must not grow while another thread iterates it.
        zero = dict.fromkeys(self.serials, 0)
        self.queued_frames: collections.Counter[int] = collections.Counter(zero)
        self.queued_camera_bytes: collections.Counter[int] = collections.Counter(zero)
        # a camera already holding its share gets no more room (it may pass it by one frame)
        self.camera_share_bytes = max_bytes // max(len(self.serials), 1)
        self._next_ticket = dict.fromkeys(self.serials, 0)  # producer's
        self._flush_queued = False
        self._closing = False
        self._discard = False
        self._busy_since: float | None = None
        # the writer thread's
        self._not_written: dict[int, list[int]] = {s: [] for s in self.serials}  # tickets
        self.frames_written: collections.Counter[int] = collections.Counter(zero)
        self.bytes_written = 0
        self.sets_written = 0
        self.sets_not_written = 0  # every member's frame was not written
        self.missing_in_sets: collections.Counter[int] = collections.Counter(zero)
        self.not_written_write_failed: collections.Counter[int] = collections.Counter(zero)
        self.not_written_at_stop: collections.Counter[int] = collections.Counter(zero)
        self.write_failing_since: float | None = None
        self.write_error = ""
        self.internal_errors = 0
        self._unflushed_capture_ns: list[int] = []
        self._latency_lock = threading.Lock()
        self._durable_latency_ns: collections.deque[int] = collections.deque(maxlen=200_000)
        self.closed = threading.Event()
        self.summary: dict[str, Any] | None = None
        self._thread = NamedThread(target=self._run, name="session-queue", daemon=True)
        self._thread.start()

    # -- the producer's side ------------------------------------------------------------------
    def put_frame(self, msg: FrameMessage, recorder_receive_unix_ns: int) -> int | None:
        """Queue a frame; its ticket (the handle sets use), or None when it does not fit."""
        nbytes = msg.left_bytes + msg.right_bytes
        with self._cv:
            serial = msg.camera_serial
            if (
                self._closing
                or self.queued_bytes + nbytes > self.max_bytes
                or self.queued_camera_bytes[serial] >= self.camera_share_bytes
            ):
                return None
            ticket = self._next_ticket[serial]
            self._next_ticket[serial] = ticket + 1
            self.queued_bytes += nbytes
            self.queued_frames[serial] += 1
            self.queued_camera_bytes[serial] += nbytes
            self._jobs.append(_Frame(msg, ticket, recorder_receive_unix_ns, nbytes))
            self._cv.notify_all()
        return ticket

    def put_gap(self, camera_serial: int, **fields: int) -> None:
        self._put(_Gap(camera_serial, fields))

    def put_event(self, kind: int, **fields: Any) -> None:
        """Queue a session event (``SessionWriter.append_event``'s arguments)."""
        self._put(_Event(kind, fields))

    def put_set(self, set_unix_ns: int, tickets: tuple[int | None, ...], spread_ns: int) -> None:
        self._put(_Set(set_unix_ns, tickets, spread_ns))

    def request_flush(self) -> None:
        """Queue a flush unless one is already waiting (a stalled writer gets one, not many)."""
        with self._cv:
            if self._flush_queued or self._closing:
                return
            self._flush_queued = True
        self._put(_Flush())

    def discard(self) -> None:
        """Write no more of the queued frames: each is counted in ``not_written_at_stop``."""
        self._discard = True

    def close(
        self, build_summary: Callable[[], dict[str, Any]], on_closed: Callable[[], None] | None
    ) -> None:
        """After the queued jobs: flush, ``build_summary()`` (on the writer thread, so it sees
        the final counts), close the file with it, call ``on_closed``; then ``closed`` is set."""
        self._put(_Close(build_summary, on_closed))
        with self._cv:
            self._closing = True

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until every queued job is done; False if that took longer than ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self._jobs or self._busy_since is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def stalled_s(self) -> float:
        """How long the writer has been inside one call, once that is over STALL_REPORT_S."""
        since = self._busy_since
        busy = time.monotonic() - since if since is not None else 0.0
        return busy if busy >= STALL_REPORT_S else 0.0

    def latency_ms(self) -> dict[str, float | None]:
        """Capture-to-durable latency of the frames flushed so far (p50, p99, max)."""
        with self._latency_lock:
            a = np.asarray(self._durable_latency_ns, dtype=np.float64) / 1e6
        if not a.size:
            return {"p50": None, "p99": None, "max": None}
        return {
            "p50": round(float(np.percentile(a, 50)), 2),
            "p99": round(float(np.percentile(a, 99)), 2),
            "max": round(float(a.max()), 2),
        }

    def _put(self, job: Any) -> None:
        with self._cv:
            self.queued_bytes += SMALL_JOB_BYTES
            self._jobs.append(job)
            self._cv.notify_all()

    # -- the writer thread --------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._jobs:
                    self._cv.wait()
                job = self._jobs.popleft()
                if isinstance(job, _Flush):
                    self._flush_queued = False
                self._busy_since = time.monotonic()
            try:
                self._do(job)
            except Exception:  # a bug must not end the writing of the take
                self.internal_errors += 1
                if self.internal_errors <= 5 or self.internal_errors % 1000 == 0:
                    log.exception(
                        "%s: internal error #%d writing a %s",
                        self.writer.path,
                        self.internal_errors,
                        type(job).__name__.strip("_").lower(),
                    )
                if isinstance(job, _Frame):
                    self._not_written[job.msg.camera_serial].append(job.ticket)
                    self.not_written_write_failed[job.msg.camera_serial] += 1
            finally:
                with self._cv:
                    self._busy_since = None
                    if isinstance(job, _Frame):
                        self.queued_bytes -= job.nbytes
                        self.queued_frames[job.msg.camera_serial] -= 1
                        self.queued_camera_bytes[job.msg.camera_serial] -= job.nbytes
                    else:
                        self.queued_bytes -= SMALL_JOB_BYTES
                    self._cv.notify_all()
            if isinstance(job, _Close):
                self.closed.set()
                return

    def _do(self, job: Any) -> None:
        if isinstance(job, _Frame):
            self._write_frame(job)
        elif isinstance(job, _Set):
            self._write_set(job)
        elif isinstance(job, _Gap):
            try:
                self.writer.append_gap(job.camera_serial, **job.fields)
            except SessionWriteError as exc:  # the record is kept; the next flush retries it
                self._failed(exc)
        elif isinstance(job, _Event):
            try:
                self.writer.append_event(job.kind, **job.fields)
            except SessionWriteError as exc:  # the event is kept; the next flush retries it
                self._failed(exc)
        elif isinstance(job, _Flush):
            self._flush()
        else:
            self._close(job)

    def _write_frame(self, job: _Frame) -> None:
        msg = job.msg
        serial = msg.camera_serial
        if self._discard:
            self._not_written[serial].append(job.ticket)
            self.not_written_at_stop[serial] += 1
            return
        try:
            row = self.writer.append_frame(
                serial,
                left=msg.left,
                right=msg.right,
                capture_unix_ns=msg.capture_unix_ns,
                host_receive_unix_ns=msg.host_receive_unix_ns,
                recorder_receive_unix_ns=job.recorder_receive_unix_ns,
                frame_index=msg.frame_index,
                seq=msg.seq,
                ptp_offset_ns=msg.ptp_offset_ns,
                ptp_locked=msg.ptp_locked,
            )
        except SessionWriteError as exc:
            self._failed(exc)
            self._not_written[serial].append(job.ticket)
            self.not_written_write_failed[serial] += 1
            return
        expected = job.ticket - len(self._not_written[serial])
        if row != expected:  # tickets and rows must agree, or sets would point at other frames
            raise RuntimeError(f"camera {serial}: frame row {row}, expected {expected}")
        self.frames_written[serial] += 1
        self.bytes_written += job.nbytes
        self._unflushed_capture_ns.append(msg.capture_unix_ns)

    def _row(self, serial: int, ticket: int | None) -> int:
        """The file row of a camera's ticket; -1 for none or a frame that was not written."""
        if ticket is None:
            return -1
        not_written = self._not_written[serial]
        k = bisect.bisect_right(not_written, ticket)
        if k and not_written[k - 1] == ticket:
            return -1
        return ticket - k

    def _write_set(self, job: _Set) -> None:
        rows = tuple(self._row(s, t) for s, t in zip(self.serials, job.tickets, strict=True))
        if all(r == -1 for r in rows):
            self.sets_not_written += 1
            return
        try:
            self.writer.append_set(job.set_unix_ns, rows, job.spread_ns)
        except SessionWriteError as exc:  # the set is kept; the next flush retries it
            self._failed(exc)
        self.sets_written += 1
        # counted as the file's readers count it (protocol/set_counts.py), sets written only
        self.missing_in_sets.update(missing_in_sets([rows], self.serials))

    def _flush(self) -> None:
        try:
            self.writer.flush()
        except SessionWriteError as exc:
            self._failed(exc)
            return
        if self.write_failing_since is not None:
            log.warning(
                "%s: the session file is written again after %.1f s of failures",
                self.writer.path,
                time.monotonic() - self.write_failing_since,
            )
            self.write_failing_since = None
        now = time.time_ns()
        with self._latency_lock:
            self._durable_latency_ns.extend(now - c for c in self._unflushed_capture_ns)
        self._unflushed_capture_ns.clear()

    def _failed(self, exc: SessionWriteError) -> None:
        self.write_error = str(exc)
        if self.write_failing_since is None:
            self.write_failing_since = time.monotonic()
            log.error("%s; frames are refused until it is writable again", exc)

    def _close(self, job: _Close) -> None:
        summary: dict[str, Any] = {}
        try:
            self._flush()  # for the last frames' latency; close() flushes (and reports) anyway
            summary = job.build_summary()
            self.writer.close(time.time_ns(), summary)
        except SessionWriteError as exc:
            # The file is closed without the clean mark and holds what the last good flush put
            # there; every frame after that is in the counts or in this error.
            summary["write_error"] = str(exc)
            log.error("%s", exc)
        except Exception:
            self.writer.abort()  # closed, not marked clean; the caller counts the error
            raise
        finally:
            self.summary = summary
            if job.on_closed is not None:
                try:
                    job.on_closed()
                except Exception:
                    log.exception("%s: after closing the file", self.writer.path)


def open_writer(factory: Callable[[], SessionWriter], timeout_s: float) -> SessionWriter:
    """``factory()`` (a new ``SessionWriter``) on a thread of its own, waited for at most
    ``timeout_s``: creating a file on a stalled disk blocks, and the caller must not. On time
    out raises ``TimeoutError``; a writer that is created later is closed and its file removed
    (it holds no frame). The factory's own errors are raised here."""
    lock = threading.Lock()
    done = threading.Event()
    box: dict[str, Any] = {"abandoned": False}

    def run() -> None:
        writer, error = None, None
        try:
            writer = factory()
        except BaseException as exc:  # handed to the caller
            error = exc
        with lock:
            box["writer"], box["error"] = writer, error
            abandoned = box["abandoned"]
            done.set()
        if abandoned and writer is not None:
            log.warning("%s: created after the start gave up on it; removed", writer.path)
            writer.abort()
            writer.path.unlink(missing_ok=True)

    NamedThread(target=run, name="session-open", daemon=True).start()
    done.wait(timeout_s)
    with lock:
        if not done.is_set():
            box["abandoned"] = True
            raise TimeoutError(f"creating the session file took over {timeout_s:g} s")
    if box["error"] is not None:
        raise box["error"]
    return box["writer"]
