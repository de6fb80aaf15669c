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

Neither bounds damage in metadata without a checksum, above all HDF5's global heap (every string
attribute), whose parser can loop forever; so ``protocol.session.probe.open_hdf5`` first reads
all of a file's metadata in a child process with a time limit, and opens it with
``open_unprobed`` only after that finished (imports run one way: the probe uses this module,
not the reverse). Where the ctypes binding cannot be found (not Linux, or an h5py that links
HDF5 statically) the child's retries are not capped, and the time limit alone refuses the file.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import h5py

from protocol.session.format import SessionFormatError

logger = logging.getLogger(__name__)

SIGNATURE = b"\x89HDF\r\n\x1a\n"
METADATA_READ_ATTEMPTS = 25
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

    def byte(at: int) -> int:
        if at >= len(head):  # a file cut inside its superblock (even right after the signature)
            raise SessionFormatError(
                f"{path}: the HDF5 superblock is cut short ({len(head)} bytes after its start); "
                "the file is damaged. Copy it again from the recorder"
            )
        return head[at]

    def field(at: int, width: int) -> int:
        byte(at + width - 1)
        value = int.from_bytes(head[at : at + width], "little")
        return -1 if value == (1 << (8 * width)) - 1 else value

    version = byte(8)
    if version in (0, 1):
        width = byte(13)
        base_at = 24 if version == 0 else 28
        flags = field(20, 4)
    elif version in (2, 3):
        width = byte(9)
        base_at = 12
        flags = byte(11)
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


def _fapl(cache_bytes: int, cache_slots: int) -> h5py.h5p.PropFAID:
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    settings = list(fapl.get_cache())
    settings[1], settings[2] = cache_slots, cache_bytes
    fapl.set_cache(*settings)
    func = _set_read_attempts()
    if func is None or func(fapl.id, METADATA_READ_ATTEMPTS) < 0:  # type: ignore[operator]
        _warn_unbounded()
    return fapl


@functools.cache
def _warn_unbounded() -> None:
    logger.warning(
        "H5Pset_metadata_read_attempts not found in the HDF5 library h5py loaded: a session with "
        "damaged metadata is refused only after the probe's time limit"
    )


def open_unprobed(path: Path, *, cache_bytes: int = 1 << 20, cache_slots: int = 521) -> h5py.File:
    """``session_probe.open_hdf5`` without the probe: only for the probe's child, or a file
    that passed it."""
    fapl = _fapl(cache_bytes, cache_slots)
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
