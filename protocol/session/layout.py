"""A session's layout, checked when it opens (``SessionReader``): every dataset there, of
the rank and type the format gives it, and no longer than the file can hold, so that a damaged
shape fails here in one line, not as a huge read later (docs/session.md, "Damaged files")."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import h5py

from protocol.session.format import GAP_COLUMNS, SessionFormatError, SessionInfo

# What reading a damaged file can raise, from h5py (OSError, RuntimeError, KeyError, ...), numpy
# (ValueError, IndexError, MemoryError for an absurd shape) and json (ValueError).
READ_ERRORS = (
    OSError,
    RuntimeError,
    KeyError,
    ValueError,
    TypeError,
    IndexError,
    MemoryError,
    OverflowError,
    AttributeError,
)


def check_layout(
    path: Path, f: h5py.File, info: SessionInfo, table_columns: Iterable[str], size_bytes: int
) -> None:
    """Every dataset there, 1-D (members 2-D), of an integer type, and no longer than the
    file can hold; ``table_columns`` are a camera's frame table's in this file's version."""
    n_cams = len(info.camera_serials)
    wanted: list[tuple[str, int, int]] = [  # (name, rank, columns of a 2-D table)
        ("sets/set_unix_ns", 1, 0),
        ("sets/members", 2, n_cams),
        ("sets/spread_ns", 1, 0),
        *((f"gaps/{name}", 1, 0) for name in GAP_COLUMNS),
    ]
    for serial in info.camera_serials:
        wanted += [(f"cameras/{serial}/{name}", 1, 0) for name in table_columns]
    for name, rank, columns in wanted:
        try:
            ds = f[name]
            if not isinstance(ds, h5py.Dataset):
                raise TypeError("is not a dataset")
            shape, dtype = ds.shape, ds.dtype
        except READ_ERRORS as exc:
            raise SessionFormatError(
                f"{path}: a session with a missing or bad part: no readable {name} "
                f"({exc}); the file is "
                "damaged or was not written by SessionWriter"
            ) from None
        if (
            shape is None
            or len(shape) != rank
            or (rank == 2 and shape[1] != columns)
            or dtype.kind not in "iu"
        ):
            raise SessionFormatError(
                f"{path}: {name} has shape {shape} and type {dtype}; a session's is "
                f"{'(rows,)' if rank == 1 else f'(rows, {columns})'} of integers. The file "
                "is damaged"
            )
        if shape[0] * dtype.itemsize * max(columns, 1) > size_bytes:
            raise SessionFormatError(
                f"{path}: {name} claims {shape[0]} rows, more than a file of "
                f"{size_bytes} bytes can hold; the file is damaged"
            )
    for serial in info.camera_serials:
        for side in ("left", "right"):
            name = f"cameras/{serial}/{side}_bytes"
            try:
                ds = f[name]
                ok = isinstance(ds, h5py.Dataset) and ds.ndim == 1 and ds.dtype.itemsize == 1
            except READ_ERRORS:
                ok = False
            if not ok:
                raise SessionFormatError(
                    f"{path}: {name} is missing or not a 1-D byte dataset; the file is damaged"
                )
