"""Opening a session file so that no damage can hang the reader.

A session is opened in SWMR-read mode, which also opens the files of a live or killed writer.
Two things HDF5 does differently in that mode made damaged files hang the tools:

1. **No end-of-file check.** HDF5 compares the file's size with the end-of-file address in its
   superblock and refuses a truncated file, but not for a SWMR reader (the writer may be
   growing the file). So ``check_superblock`` reads the superblock itself (versions 0-3, the
   signature at 0, 512, 1024, ...) and refuses a file shorter than its stored end of file, with
   how much is missing. A SWMR writer stores the end of file when it switches to SWMR mode and
   never lowers it, so the check holds for a killed writer's file too (its size is only larger).
2. **Metadata read retries with exponential back-off.** A SWMR reader retries a metadata read
   whose checksum fails (a writer may be half-way through writing it), 100 times by default,
   sleeping 1 ns, 2 ns, 4 ns, ... between tries: 30 tries take about 1 s, 100 never end. Any
   truncation or flipped byte in metadata hit that loop. ``open_hdf5`` sets the attempts to
   ``METADATA_READ_ATTEMPTS`` (25: at most about 35 ms of back-off per damaged object, still
   plenty for a live writer's torn read) with ``H5Pset_metadata_read_attempts``, which h5py
   does not wrap, through ctypes on the HDF5 library h5py has loaded.

Where that library cannot be found (not Linux, or an h5py that links HDF5 statically), the open
is first tried in a child process with a time limit that opens the file and touches all of its
metadata (``_probe``): slower (about a second), but bounded, and only then is it opened here.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import h5py

from protocol.session_format import SessionFormatError

logger = logging.getLogger(__name__)

SIGNATURE = b"\x89HDF\r\n\x1a\n"
METADATA_READ_ATTEMPTS = 25
PROBE_TIMEOUT_S = 30.0
_UNDEFINED = "undefined"


@dataclass(frozen=True)
class Superblock:
    """The fields of an HDF5 superblock that say where the file ends."""

    offset: int  # where the superblock is (0, or after a user block)
    version: int
    base_address: int
    end_of_file: int  # the stored end-of-file address
    consistency_flags: int  # v3: bit 0 open for writing, bit 2 SWMR writing


def _locate(path: Path, size: int) -> tuple[int, bytes]:
    with open(path, "rb") as f:
        where = 0
        while where + len(SIGNATURE) <= size:
            f.seek(where)
            head = f.read(128)
            if head.startswith(SIGNATURE):
                return where, head
            where = 512 if where == 0 else where * 2
    raise SessionFormatError(
        f"{path}: not an HDF5 file, so not an EgoSurg session; pass the .h5 file the recorder wrote"
    )


def read_superblock(path: Path) -> Superblock:
    """Parse the superblock (versions 0 to 3); ``SessionFormatError`` if it is not one."""
    size = path.stat().st_size
    where, head = _locate(path, size)
    version = head[8]

    def field(at: int, width: int) -> int:
        if at + width > len(head):
            raise SessionFormatError(
                f"{path}: the HDF5 superblock is cut short; the file is damaged"
            )
        value = int.from_bytes(head[at : at + width], "little")
        return -1 if value == (1 << (8 * width)) - 1 else value

    if version in (0, 1):
        width = head[13]
        base_at = 24 if version == 0 else 28
        flags = field(20, 4)
    elif version in (2, 3):
        width = head[9]
        base_at = 12
        flags = head[11]
    else:
        raise SessionFormatError(
            f"{path}: HDF5 superblock version {version} is unknown (0-3 are); the file is damaged "
            "or from a much newer HDF5"
        )
    if width not in (2, 4, 8):
        raise SessionFormatError(
            f"{path}: the HDF5 superblock gives {width}-byte addresses; the file is damaged"
        )
    base = field(base_at, width)
    eof = field(base_at + 2 * width, width)
    if base < 0 or eof < 0:
        raise SessionFormatError(
            f"{path}: the HDF5 superblock has no valid base or end-of-file address; the file is "
            "damaged. Copy it again from the recorder, or try 'egosurg session recover'"
        )
    return Superblock(where, version, base, eof, flags)


def check_superblock(path: Path) -> Superblock:
    """Refuse a file shorter than the end of file its superblock records (a truncated copy)."""
    sb = read_superblock(path)
    size = path.stat().st_size
    if size < sb.end_of_file:
        raise SessionFormatError(
            f"{path}: truncated: the file is {size} bytes but HDF5 recorded its end at byte "
            f"{sb.end_of_file} ({sb.end_of_file - size} bytes missing; an interrupted copy or a "
            "full disk?). Copy it again from the recorder; 'egosurg session recover' saves what "
            "can still be read"
        )
    return sb


@functools.cache
def _set_read_attempts() -> object | None:
    """``H5Pset_metadata_read_attempts`` of the HDF5 library that h5py uses, or None."""
    try:
        with open("/proc/self/maps") as maps:
            libs = {line.split()[-1] for line in maps if ".so" in line}
    except OSError:
        return None
    for lib in sorted(libs):
        name = os.path.basename(lib)
        if name.startswith("libhdf5") and not name.startswith("libhdf5_hl"):
            try:
                func = ctypes.CDLL(lib).H5Pset_metadata_read_attempts
            except (OSError, AttributeError):
                continue
            func.argtypes = [ctypes.c_int64, ctypes.c_uint]
            func.restype = ctypes.c_int
            return func
    return None


def _fapl(cache_bytes: int, cache_slots: int) -> tuple[h5py.h5p.PropFAID, bool]:
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    settings = list(fapl.get_cache())
    settings[1], settings[2] = cache_slots, cache_bytes
    fapl.set_cache(*settings)
    func = _set_read_attempts()
    bounded = func is not None and func(fapl.id, METADATA_READ_ATTEMPTS) >= 0  # type: ignore[operator]
    return fapl, bounded


def open_hdf5(path: Path, *, cache_bytes: int, cache_slots: int) -> h5py.File:
    """Open a (checked) session file read-only, SWMR where its format allows, never hanging."""
    fapl, bounded = _fapl(cache_bytes, cache_slots)
    if not bounded:
        _probe_in_child(path)
    name = os.fsencode(path)
    errors = []
    # SWMR also opens live and killed writers' files; a file older than the 1.10 format only
    # opens without it.
    for flags in (h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, h5py.h5f.ACC_RDONLY):
        try:
            return h5py.File(h5py.h5f.open(name, flags, fapl=fapl))
        except (OSError, RuntimeError, ValueError, KeyError) as exc:
            errors.append(str(exc))
    raise SessionFormatError(
        f"{path}: HDF5 cannot open it ({errors[0]}); the file is damaged. Copy it again from the "
        "recorder"
    )


def _probe_in_child(path: Path) -> None:
    """Open ``path`` and read all of its metadata in a child process with a time limit."""
    try:
        out = subprocess.run(
            [sys.executable, "-c", _PROBE, os.fspath(path)],
            capture_output=True,
            text=True,
            timeout=PROBE_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        raise SessionFormatError(
            f"{path}: HDF5 did not finish reading its metadata in {PROBE_TIMEOUT_S:g} s; the file "
            "is damaged. Copy it again from the recorder"
        ) from None
    if out.returncode != 0:
        reason = (out.stderr.strip().splitlines() or ["unknown error"])[-1]
        raise SessionFormatError(f"{path}: HDF5 cannot read its metadata ({reason}); damaged")


# Every object, attribute and chunk index: all the metadata a reader can touch.
_PROBE = """
import sys, h5py
with h5py.File(sys.argv[1], "r", swmr=True) as f:
    def visit(name, obj):
        dict(obj.attrs)
        if isinstance(obj, h5py.Dataset) and obj.chunks:
            for i in range(obj.id.get_num_chunks()):
                obj.id.get_chunk_info(i)
    dict(f.attrs)
    f.visititems(visit)
"""
