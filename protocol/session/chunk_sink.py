"""Writing whole chunks of a session file at known file offsets, from a thread of their own.

``SessionWriter`` hands every filled 1 MiB image chunk to a ``ChunkSink`` and goes on
receiving: a background thread writes it with ``os.pwrite``, which releases the GIL, so the
writing overlaps the recorder's receiving and synchronising. HDF5 still owns the file's layout:
the image datasets allocate their chunks when they grow (``H5D_ALLOC_TIME_EARLY``, no fill
writes), the writer asks HDF5 where each chunk lives, and the sink writes the bytes there. The
chunks are stored unfiltered, so these are exactly the bytes HDF5 itself would have written.

Direct I/O. Where the file system takes it, the sink writes with ``O_DIRECT``: the bytes go
from the page-aligned chunk buffer to the disk without being copied into the page cache. On the
2-core development VM, writing 1 GiB in 1 MiB blocks cost 0.06 s of CPU that way, against
0.16-0.6 s through a warm page cache and up to 2.5 s through pages the VM had not touched yet
(``bench/bench_capture.py`` part 2 measures both on the session's own payloads). It also
keeps a long recording from evicting everything else from the cache. Direct writes need the
file offset, the length and the buffer aligned to the device's block (``DIRECT_ALIGN_BYTES``
covers 512 and 4096 byte sectors); the session file is created with its large allocations
aligned that way. A write the file system refuses with ``EINVAL`` (no direct I/O there) is
done through an ordinary descriptor instead, and so are all later ones.

Failures. A write that fails (disk full, I/O error) is kept, buffer and all, and retried: by
``drain()``, which every flush calls and which raises ``OSError`` while a retry still fails,
and by ``check()``, which the writer calls before it appends a frame. So a failure loses
nothing that was handed over, and the caller learns of it before it records rows that point
at unwritten bytes.
"""

from __future__ import annotations

import logging
import mmap
import os
import threading
from collections import deque
from pathlib import Path

import numpy as np

from protocol.os_thread import NamedThread

logger = logging.getLogger(__name__)

DIRECT_ALIGN_BYTES = 4096
_DEFAULT_DEPTH_CHUNKS = 16  # chunks queued ahead of the thread: 16 MiB, about 13 ms at 1.2 GB/s


def _pwrite(fd: int, data: memoryview, offset: int) -> int:
    """The one write call (a seam for the tests' fault injection)."""
    return os.pwrite(fd, data, offset)


class ChunkSink:
    """Writes whole chunks to one file from a background thread; see the module docstring.

    ``take_buffer()`` lends a page-aligned chunk buffer, ``submit()`` queues it for writing
    (the sink takes it back once written), ``write_now()`` writes one synchronously after
    everything queued, ``drain()`` waits for the queue. Use it from one producer thread.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        chunk_bytes: int,
        *,
        direct_io: bool | None = None,
        depth_chunks: int = _DEFAULT_DEPTH_CHUNKS,
        buffers_held: int = 0,
    ) -> None:
        """``direct_io``: None uses ``O_DIRECT`` where the file system takes it, True requires
        it, False never uses it. ``buffers_held``: how many buffers the producer keeps lent at
        once (its unfinished chunks); the sink allocates up to that plus ``depth_chunks``."""
        if chunk_bytes <= 0:
            raise ValueError(f"chunk_bytes must be > 0, got {chunk_bytes}")
        if depth_chunks <= 0:
            raise ValueError(f"depth_chunks must be > 0, got {depth_chunks}")
        self.path = Path(path)
        self.chunk_bytes = chunk_bytes
        self._fd = os.open(self.path, os.O_WRONLY | getattr(os, "O_CLOEXEC", 0))
        self._direct_fd = -1
        aligned = chunk_bytes % DIRECT_ALIGN_BYTES == 0
        if direct_io and not (aligned and hasattr(os, "O_DIRECT")):
            os.close(self._fd)
            raise ValueError(
                f"direct I/O needs chunks of a multiple of {DIRECT_ALIGN_BYTES} bytes on Linux; "
                f"got {chunk_bytes} bytes on {os.name}"
            )
        if direct_io is not False and aligned and hasattr(os, "O_DIRECT"):
            try:
                self._direct_fd = os.open(self.path, os.O_WRONLY | os.O_DIRECT)
            except OSError as exc:
                if direct_io:
                    os.close(self._fd)
                    raise
                logger.info("%s: no direct I/O on this file system (%s)", self.path, exc)
        self._limit = buffers_held + depth_chunks
        self._allocated = 0
        self._free: list[np.ndarray] = []
        self._jobs: deque[tuple[np.ndarray, int]] = deque()
        self._failed: list[tuple[np.ndarray, int]] = []
        self._error: OSError | None = None
        self._writing = False
        self._closing = False
        self._cv = threading.Condition()
        self._thread = NamedThread(target=self._run, name="session-writer", daemon=True)
        self._thread.start()

    @property
    def direct_io(self) -> bool:
        """Whether writes currently go past the page cache."""
        return self._direct_fd >= 0

    # -- the producer's side ------------------------------------------------------------------
    def take_buffer(self) -> np.ndarray:
        """A chunk buffer (page-aligned, old contents); waits while all are queued."""
        with self._cv:
            while not self._free:
                # Never wait for a thread with nothing to do: after failed writes, lend more.
                idle = not self._jobs and not self._writing
                if self._allocated < self._limit or idle:
                    self._allocated += 1
                    return np.frombuffer(mmap.mmap(-1, self.chunk_bytes), dtype=np.uint8)
                self._cv.wait()
            return self._free.pop()

    def give_back(self, buffer: np.ndarray) -> None:
        """Return a lent buffer that holds nothing to write."""
        with self._cv:
            self._free.append(buffer)
            self._cv.notify_all()

    def submit(self, buffer: np.ndarray, file_offset: int) -> None:
        """Queue a full chunk for writing at ``file_offset``; the buffer is the sink's again."""
        with self._cv:
            self._jobs.append((buffer, file_offset))
            self._cv.notify_all()

    def write_now(self, buffer: np.ndarray, file_offset: int) -> None:
        """Write one chunk in this thread, after everything queued; raises ``OSError``."""
        self.drain()
        self._write(buffer, file_offset)

    def drain(self) -> None:
        """Wait until every queued chunk is written, retry failed ones; raise if one fails."""
        with self._cv:
            while self._jobs or self._writing:
                self._cv.wait()
            failed, self._failed = self._failed, []
            self._error = None
        for k, (buffer, offset) in enumerate(failed):
            try:
                self._write(buffer, offset)
            except OSError as exc:
                with self._cv:
                    self._failed = failed[k:] + self._failed
                    self._error = exc
                raise
            self.give_back(buffer)

    def check(self) -> None:
        """Raise ``OSError`` if an earlier write failed and still fails on a retry."""
        if self._error is not None:
            self.drain()

    def close(self) -> None:
        """Stop the thread and close the file (queued chunks are written first; failed ones
        are dropped: call ``drain()`` before to know)."""
        with self._cv:
            if self._closing:
                return
            self._closing = True
            self._cv.notify_all()
        self._thread.join()
        for fd in (self._fd, self._direct_fd):
            if fd >= 0:
                os.close(fd)
        self._fd = self._direct_fd = -1

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._jobs and not self._closing:
                    self._cv.wait()
                if not self._jobs:
                    return
                buffer, offset = self._jobs.popleft()
                self._writing = True
            try:
                self._write(buffer, offset)
            except OSError as exc:
                with self._cv:
                    self._failed.append((buffer, offset))
                    self._error = exc
                    self._writing = False
                    self._cv.notify_all()
                continue
            with self._cv:
                self._free.append(buffer)
                self._writing = False
                self._cv.notify_all()

    def _write(self, buffer: np.ndarray, offset: int) -> None:
        data = buffer.data
        direct = self._direct_fd >= 0 and offset % DIRECT_ALIGN_BYTES == 0
        if direct:
            try:
                self._write_all(self._direct_fd, data, offset)
                return
            except OSError as exc:
                if exc.errno != 22:  # EINVAL: this file system, or this buffer, refuses it
                    raise
                logger.warning(
                    "%s: direct I/O refused (%s); writing through the cache", self.path, exc
                )
                os.close(self._direct_fd)
                self._direct_fd = -1
        self._write_all(self._fd, data, offset)

    @staticmethod
    def _write_all(fd: int, data: memoryview, offset: int) -> None:
        done = 0
        while done < len(data):
            n = _pwrite(fd, data[done:], offset + done)
            if n <= 0:
                raise OSError(5, "the write made no progress")
            done += n
