"""Files that survive a crash or SIGKILL: a reader finds the old file or the whole new one, never
a torn one, and a rename or removal is on disk once the call returns.

The case folder's index and models (``reconstructor/case/``) are written this way; the recorder's
take journal syncs its folder the same way. Standard library only: the edge may use it.
"""

from __future__ import annotations

import os
from pathlib import Path


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the whole new one, even
    after a crash or SIGKILL: a temp file in the same folder, fsync, rename, fsync the folder."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    with tmp.open("wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
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
