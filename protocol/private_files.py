"""Files only their owner reads: nearly everything the ``egosurg`` command writes can show a
patient or name a case.

Sessions, case models, PLYs, cached depth, renders, MP4s, exported frames, evaluation pictures
and the logs that name a case all show patient imagery or geometry. Rather than trusting every
writer (OpenCV, PyAV, HDF5, numpy, ``open``) to pass a mode, the ``egosurg`` entry runs each
command under the umask ``0o077`` (``owner_only_umask``): whatever the user's shell set, a new
file is at most 0600 and a new folder 0700, including those of worker processes, which inherit
the umask. A file meant for others sets its mode explicitly after creating it (a
``.recipient`` key, a link's public key: 0644).

The umask cannot narrow a file that already exists: a file opened for writing keeps its old
mode. The commands that write plaintext patient imagery where the user asks (``case export``,
``replay``, ``session export-frames``) therefore also narrow each file they wrote
(``make_owner_only``) and say so in one line on stderr (``plaintext_notice``). Standard library
only: the edge uses it too.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

OWNER_ONLY_UMASK = 0o077
FILE_MODE = 0o600
FOLDER_MODE = 0o700


@contextmanager
def owner_only_umask() -> Iterator[None]:
    """Run the body under the umask ``0o077``; the caller's umask comes back after it (a test
    that calls a command in its own process keeps its own)."""
    old = os.umask(OWNER_ONLY_UMASK)
    try:
        yield
    finally:
        os.umask(old)


def make_owner_only(path: Path) -> None:
    """Narrow a file this command wrote to 0600 (a folder to 0700): a file that existed before
    kept its old mode when it was opened for writing."""
    os.chmod(path, FOLDER_MODE if path.is_dir() else FILE_MODE)


def plaintext_notice(what: str, where: Path | str) -> str:
    """The one line a command prints on stderr after writing unencrypted patient imagery or
    geometry, so nobody mistakes an export for a protected file."""
    return (
        f"wrote plaintext {what} to {where} (owner-only: mode 0600 in folders this command made "
        "0700; delete them when done, they are not encrypted)"
    )
