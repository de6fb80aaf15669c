"""A new session file, for ``protocol.session.write``: the writer's arguments checked before
anything touches the disk, and the file created (mode 0600, never over an existing one) with
the HDF5 settings SWMR, direct I/O and the HDF5 1.10 tools need."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import h5py

from protocol.session.chunk_sink import DIRECT_ALIGN_BYTES
from protocol.session.format import SessionWriteError
from protocol.session.privacy import create_private_file

MAX_BLOB_CHUNK = 1 << 30


def check_arguments(
    serials: Sequence[int],
    *,
    session_name: str,
    case_metadata: Mapping[str, str],
    tolerance_ns: int,
    blob_chunk_bytes: int,
    previous_session_file: str,
    take_part: int,
) -> None:
    """``SessionWriter``'s arguments, checked before anything touches the disk."""
    if not serials:
        raise ValueError("a session needs at least one camera")
    if len(set(serials)) != len(serials):
        raise ValueError(f"camera serials must be unique, got {list(serials)}")
    if not session_name:
        raise ValueError("session_name must not be empty")
    if tolerance_ns <= 0:
        raise ValueError(f"tolerance_ns must be > 0, got {tolerance_ns}")
    if take_part < 1 or (take_part > 1) != bool(previous_session_file):
        raise ValueError(
            f"take_part {take_part} with previous_session_file {previous_session_file!r}: "
            "a take's first part (1) has no previous file, a later part names one"
        )
    if not 1 <= blob_chunk_bytes <= MAX_BLOB_CHUNK:
        raise ValueError(f"blob_chunk_bytes must be 1 to {MAX_BLOB_CHUNK}, got {blob_chunk_bytes}")
    bad = {k: v for k, v in case_metadata.items() if not isinstance(v, str)}
    if bad or not all(isinstance(k, str) for k in case_metadata):
        raise ValueError(f"case_metadata must map str to str; bad entries: {bad}")


def check_new_file(path: Path) -> None:
    """A session file is only ever new, in a folder that exists."""
    if path.exists():
        raise SessionWriteError(
            f"{path}: already exists; a session file is never overwritten. "
            "Choose another session name or move the old file away."
        )
    if not path.parent.is_dir():
        raise SessionWriteError(f"{path}: directory {path.parent} does not exist; create it first")


def create_file(path: Path, blob_chunk_bytes: int) -> h5py.File:
    """The new session file (mode 0600), open for writing; nothing is left behind on failure."""
    try:
        create_private_file(path)  # 0600 whatever the umask; HDF5 keeps the mode
    except FileExistsError:
        raise SessionWriteError(
            f"{path}: already exists; a session file is never overwritten."
        ) from None
    except OSError as exc:
        raise SessionWriteError(f"{path}: cannot create the session file: {exc}") from exc
    try:
        # Bounds v110..v110: SWMR needs the 1.10 file format, and pinning the upper bound
        # keeps the file readable by the HDF5 1.10 tools (h5dump) of Debian and JetPack.
        # No chunk cache: image chunks are written whole, past it, and the tables' chunks
        # are only appended to, so a cache would only add a copy (and slow flushes).
        # Allocations of a whole image chunk start on a disk block, as direct I/O needs.
        aligned = blob_chunk_bytes % DIRECT_ALIGN_BYTES == 0
        return h5py.File(
            path,
            "w",  # the empty file created above, exclusively
            libver=("v110", "v110"),
            rdcc_nbytes=0,
            alignment_threshold=blob_chunk_bytes if aligned else 1,
            alignment_interval=DIRECT_ALIGN_BYTES if aligned else 1,
        )
    except OSError as exc:
        path.unlink(missing_ok=True)
        raise SessionWriteError(f"{path}: cannot create the session file: {exc}") from exc
