"""Files that survive a crash or SIGKILL: a reader finds the old file or the whole new one, never
a torn one, and a rename or removal is on disk once the call returns.

The case folder's index and models (``reconstructor/case/``) are written this way; the recorder's
take journal syncs its folder the same way. Standard library only: the edge may use it.
"""

from __future__ import annotations

import os
from pathlib import Path


def atomic_write_bytes(path: Path, data: bytes, *, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the whole new one, even
    after a crash or SIGKILL: a temp file in the same folder, fsync, rename, fsync the folder.
    ``mode``: the file's permissions from its creation on (``0o600`` for anything that names a
    patient), never wider for a moment; None: the umask's default."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC
    fd = os.open(tmp, flags, 0o666 if mode is None else mode)
    try:
        if mode is not None:
            os.fchmod(fd, mode)  # an earlier partial file of the same name kept its own mode
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def fsync_dir(folder: Path) -> None:
    """Make the folder's entries durable: a rename, creation or removal in it survives a crash
    only once the folder itself is synced."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
