"""Reading a session file's metadata first in a child process, so that no damage hangs or
crashes the caller.

Why a child. Capping HDF5's metadata read retries (``protocol.session.open``) bounds damage in
the metadata that carries a checksum, but not in what has none. The global heap, where HDF5
keeps every variable-length string (all the string attributes of a session), has none, and its
parser (``H5HG__cache_heap_deserialize``, HDF5 1.8 to 2.0) walks the objects of a heap
collection by their stored sizes: a free-space entry (index 0) whose size reads 0, which a
zeroed range or a changed length field in front of it produces, makes it loop forever without
reading anything, inside one ``H5Aread``. No timer in the calling process can stop a C loop that
holds the GIL, and the next unchecked structure would do the same, so the first open of a file is
done by a child: it opens the file as ``open_hdf5`` does and reads every object header and every
attribute of every object (all of a session's metadata a reader touches; the chunk indexes are
checksummed), reporting each object it enters on a pipe. If it stops making progress for
``PROBE_STALL_S`` (or runs past ``PROBE_TOTAL_S``) it is killed and the file is refused with a
``SessionFormatError`` naming the object; if it dies (HDF5 crashing on the damage), likewise.
Errors HDF5 raises in the child are not judged here: the caller meets them again when it reads
and reports them as it always has (``protocol.session.read``), which lets ``session recover``
save what the rest of a damaged file holds.

Cost. The child is forked when the caller has a single Python thread (about 10-20 ms on a
small session: h5py is already loaded, nothing is imported again). With other threads running, a
fork could copy a lock some thread holds (h5py's, the logging module's), so the child is a new
interpreter instead (about 0.5 s, importing h5py). A file that passed is remembered by device,
inode, size and modification time, so opening it again in the same process costs nothing; a live
file that grows is probed again.
"""

from __future__ import annotations

import collections
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
from h5py._objects import phil  # h5py's global lock: held across fork so no thread owns it

from protocol.session.format import SessionFormatError
from protocol.session.open import open_unprobed

logger = logging.getLogger(__name__)

PROBE_STALL_S = 10.0  # one object's header and attributes take milliseconds; more is a loop
PROBE_TOTAL_S = 300.0  # a backstop for the whole walk (a session has hundreds of objects)
_REMEMBERED_FILES = 64
_BATCH_S = 0.005
_REPO = Path(__file__).resolve().parents[1]

_lock = threading.Lock()
_passed: collections.OrderedDict[tuple[int, int, int, int], None] = collections.OrderedDict()


def probe_metadata(path: Path, opener: Callable[[], h5py.File]) -> None:
    """Read all of ``path``'s metadata in a child, bounded in time; ``SessionFormatError`` if
    HDF5 hangs or crashes on it. ``opener`` opens it as the caller will (fork only)."""
    key = _file_key(path)
    with _lock:
        if key in _passed:
            _passed.move_to_end(key)
            return
    started = time.monotonic()
    if threading.active_count() == 1 and hasattr(os, "fork"):
        how = "fork"
        _probe_forked(path, opener)
    else:
        how = "new interpreter"
        _probe_spawned(path)
    logger.debug("%s: metadata probed (%s) in %.3f s", path, how, time.monotonic() - started)
    if _file_key(path) == key:  # unchanged while it was probed
        with _lock:
            _passed[key] = None
            while len(_passed) > _REMEMBERED_FILES:
                _passed.popitem(last=False)


def _file_key(path: Path) -> tuple[int, int, int, int]:
    st = path.stat()
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


# -- the parent's side


def _probe_forked(path: Path, opener: Callable[[], h5py.File]) -> None:
    read_fd, write_fd = os.pipe()
    with phil:
        pid = os.fork()
    if pid == 0:  # the child: never return into the caller's stack
        code = 0
        try:
            os.close(read_fd)
            logging.disable(logging.CRITICAL)  # the parent reports; the child only walks
            _walk(opener, lambda line: os.write(write_fd, line.encode("utf-8", "replace")))
        except BaseException:
            code = 1
        finally:
            os._exit(code)
    os.close(write_fd)
    try:
        done, last = _follow(read_fd, path)
    except BaseException:
        _kill(pid)
        raise
    finally:
        os.close(read_fd)
    _, status = os.waitpid(pid, 0)
    if not done:
        _crashed(path, last, os.waitstatus_to_exitcode(status))


def _probe_spawned(path: Path) -> None:
    code = "import sys; from protocol.session.probe import child_main; child_main(sys.argv[1])"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(_REPO), *sys.path]))
    proc = subprocess.Popen(
        [sys.executable, "-c", code, os.fspath(path)],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    assert proc.stdout is not None
    try:
        done, last = _follow(proc.stdout.fileno(), path)
    except BaseException:
        proc.kill()
        raise
    finally:
        proc.stdout.close()
        proc.wait()
    if not done:
        _crashed(path, last, proc.returncode)


def _follow(fd: int, path: Path) -> tuple[bool, str]:
    """Read the child's progress until it ends: (whether it finished the walk, last object)."""
    deadline = time.monotonic() + PROBE_TOTAL_S
    buffered, last, done = b"", "the file's superblock", False
    while True:
        wait_s = min(PROBE_STALL_S, deadline - time.monotonic())
        ready = select.select([fd], [], [], max(wait_s, 0.0))[0] if wait_s > 0 else []
        if not ready:
            limit_s = PROBE_STALL_S if wait_s >= PROBE_STALL_S else PROBE_TOTAL_S
            raise SessionFormatError(
                f"{path}: the file's metadata is damaged (HDF5 did not finish reading {last} in "
                f"{limit_s:g} s). Copy the file again from the recorder; as it is, it cannot be "
                "read"
            )
        chunk = os.read(fd, 1 << 16)
        if not chunk:
            return done, last
        time.sleep(_BATCH_S)  # let lines gather: one wake-up per object made the probe 2x slower
        *lines, buffered = (buffered + chunk).split(b"\n")
        for line in lines:
            kind, _, text = line.decode("utf-8", "replace").partition(" ")
            if kind == "enter":
                last = text
            elif kind == "error":
                logger.debug("%s: metadata probe: %s", path, text)
            elif kind == "done":
                done = True


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


def _crashed(path: Path, last: str, returncode: int) -> None:
    """The child ended before finishing the walk: ``returncode`` as ``Popen`` gives it."""
    if returncode < 0:
        try:
            how = f"crashed ({signal.Signals(-returncode).name})"
        except ValueError:
            how = f"crashed (signal {-returncode})"
    else:
        how = f"stopped (exit status {returncode})"
    raise SessionFormatError(
        f"{path}: the file's metadata is damaged (HDF5 {how} reading {last}). Copy the file "
        "again from the recorder; as it is, it cannot be read"
    )


# -- the child's side


def _walk(opener: Callable[[], h5py.File], emit: Callable[[str], object]) -> None:
    """Open the file and read every object header and attribute, saying where it is. (h5py's
    low-level calls: its high-level objects cost about 0.4 ms each, most of the walk.)"""
    try:
        f = opener()
    except BaseException as exc:  # the caller's own open reports it
        emit(f"error {_one_line(exc)}\ndone\n")
        return
    with f:
        emit("enter the root group's attributes\n")
        _read_attributes(f.id, b".", emit)

        def visit(name: bytes) -> None:
            emit(f"enter the attributes of /{_one_line(name.decode('utf-8', 'replace'))}\n")
            _read_attributes(f.id, name, emit)

        try:
            h5py.h5o.visit(f.id, visit)
        except Exception as exc:
            emit(f"error walking the groups: {_one_line(exc)}\n")
    emit("done\n")


def _read_attributes(fid: h5py.h5f.FileID, name: bytes, emit: Callable[[str], object]) -> None:
    """Read each attribute of object ``name`` (its values too: strings live in the global heap)."""
    try:
        oid = h5py.h5o.open(fid, name)
        for i in range(h5py.h5a.get_num_attrs(oid)):
            try:
                aid = h5py.h5a.open(oid, index=i)
                if aid.get_space().get_simple_extent_type() != h5py.h5s.NULL:
                    aid.read(np.empty(aid.shape, dtype=aid.dtype))
            except Exception as exc:
                emit(f"error {_one_line(name)} attribute {i}: {_one_line(exc)}\n")
    except Exception as exc:
        emit(f"error {_one_line(name)} attributes: {_one_line(exc)}\n")


def _one_line(value: object) -> str:
    return " ".join(str(value).split())[:300]


def child_main(path: str) -> None:
    """The new-interpreter child: walk ``path`` opened as ``open_hdf5`` opens it."""
    out = sys.stdout.buffer

    def emit(line: str) -> None:
        out.write(line.encode("utf-8", "replace"))
        out.flush()

    logging.disable(logging.CRITICAL)
    _walk(lambda: open_unprobed(Path(path)), emit)


def open_hdf5(path: Path, *, cache_bytes: int, cache_slots: int) -> h5py.File:
    """Open a (checked) session file read-only, SWMR where its format allows, never hanging:
    its metadata is read first in a child with a time limit (``probe_metadata``)."""
    probe_metadata(path, lambda: open_unprobed(path))
    return open_unprobed(path, cache_bytes=cache_bytes, cache_slots=cache_slots)
