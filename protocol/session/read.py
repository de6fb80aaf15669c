"""Reading a session file: finished, being written, or left by a killed writer.

See ``protocol.session`` for the overview and ``docs/session.md`` for the layout. Readers locate
every image by offset and length, so they read files of any blob chunking (1 MiB in the files of
the first recorders, larger since).

Damaged files. The file is checked against its superblock's end of file and opened so that no
metadata read can hang (``protocol.session.open``); its layout (every dataset's presence, rank,
type and a length the file can hold) is checked when it opens; and any error HDF5, numpy or JSON
raise while reading it later becomes a ``SessionFormatError`` that names the file and the part
(``_guarded``). Asking for a camera the session does not have (``KeyError``) or a row past the
end (``IndexError``) stays the caller's error.

Checked images. ``frame_bytes`` compares every image it returns with the XXH3-64 stored when it
was recorded (format_version 2 on), so no caller uses a changed image unnoticed; a mismatch is
an ``ImageChecksumError`` naming the camera, row and side, and each command decides whether it
refuses the file or skips that frame (docs/session.md lists which). The cost is one hash over
bytes just read from disk: XXH3 runs at several GB/s, against HDF5's read of the same bytes.
"""

from __future__ import annotations

import functools
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import h5py
import numpy as np
import xxhash

from protocol.session.format import (
    EVENT_COLUMNS,
    FORMAT,
    FORMAT_VERSION,
    GAP_COLUMNS,
    OLDEST_FORMAT_VERSION,
    SUMMARY_COLUMNS,
    CameraInfo,
    EventKind,
    GapKind,
    GapRecord,
    SessionEvent,
    SessionFormatError,
    SessionInfo,
    SessionNotFoundError,
    SetTable,
    frame_columns,
)
from protocol.session.open import check_superblock, read_superblock
from protocol.session.probe import open_hdf5
from protocol.session.verify import verify_session
from protocol.set_counts import missing_in_sets

logger = logging.getLogger(__name__)

READ_CACHE_BYTES = 16 << 20  # per dataset: a few chunks of the byte datasets
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
_F = TypeVar("_F", bound=Callable[..., Any])
SIDES = ("left", "right")


class UnknownCameraError(KeyError):
    """The caller asked for a camera the session does not have."""


class FrameRowError(IndexError):
    """The caller asked for a frame row past the end of a camera's table."""


class ImageChecksumError(SessionFormatError):
    """An image's bytes no longer match the checksum stored when it was recorded."""

    def __init__(self, path: Path, camera_serial: int, row: int, side: str) -> None:
        self.camera_serial, self.row, self.side = camera_serial, row, side
        super().__init__(
            f"{path}: camera {camera_serial} row {row} {side} image does not match its "
            "recorded checksum (xxh3_64): its bytes changed after it was recorded; "
            "'egosurg session verify' lists every damaged image"
        )


def _guarded(what: str) -> Callable[[_F], _F]:
    """Turn any error reading the file into a ``SessionFormatError`` naming the file and part."""

    def wrap(method: _F) -> _F:
        @functools.wraps(method)
        def guarded(self: SessionReader, *args: Any, **kwargs: Any) -> Any:
            try:
                return method(self, *args, **kwargs)
            except (SessionFormatError, UnknownCameraError, FrameRowError):
                raise
            except READ_ERRORS as exc:
                raise SessionFormatError(
                    f"{self.path}: cannot read {what} ({type(exc).__name__}: {exc}); the file is "
                    "damaged. 'egosurg session recover' copies what is still intact"
                ) from None

        return guarded  # type: ignore[return-value]

    return wrap


class SessionReader:
    """Reads a session file: finished, being written, or left by a killed writer.

    Everything it returns is the consistent prefix: a frame table is as long as the shortest of
    its columns, and sets whose members are not all in the file are left out (``verify()``
    says so). Use it as a context manager. ``refresh()`` picks up rows a live writer flushed.
    """

    def __init__(self, path: str | os.PathLike[str], *, allow_truncated: bool = False) -> None:
        """``allow_truncated``: open a file shorter than the end its superblock records, for
        ``protocol.session.recover`` (what is cut off then fails as ``SessionFormatError``)."""
        self._path = Path(path)
        self._f, version = _open_session(self._path, allow_truncated)
        self.columns = frame_columns(version)  # the frame table's columns in this file
        try:
            self._size_bytes = self._path.stat().st_size
            self.info = self._read_info(version)
            self._check_layout()
        except BaseException:
            self._f.close()
            raise
        self._views: dict[int, _BlobView] = {}

    @property
    def path(self) -> Path:
        return self._path

    @property
    def h5(self) -> h5py.File:
        """The open file, for tools that read the layout directly (``session_recover``)."""
        return self._f

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> SessionReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @_guarded("the rows flushed since it was opened")
    def refresh(self) -> None:
        """See rows flushed by a live writer since opening (root attributes are not refreshed)."""
        if self._f.swmr_mode:

            def visit(_name: str, obj: object) -> None:
                if isinstance(obj, h5py.Dataset):
                    obj.refresh()

            self._f.visititems(visit)
        self._views.clear()

    # -- frames

    @_guarded("a frame table")
    def frame_count(self, camera_serial: int) -> int:
        g = self._group(camera_serial)
        return min(g[name].shape[0] for name in self.columns)

    @_guarded("a frame table")
    def frame_table(self, camera_serial: int) -> dict[str, np.ndarray]:
        """Every column of the frame table (``self.columns``: ``FRAME_COLUMNS``, without the
        checksums in a format_version 1 file) for one camera, as arrays of equal length."""
        g = self._group(camera_serial)
        n = self.frame_count(camera_serial)
        return {name: g[name][:n] for name in self.columns}

    def frame_bytes(self, camera_serial: int, row: int) -> tuple[bytes, bytes]:
        """The (left, right) encoded images of one frame, exactly as they were received.

        Each is checked against its stored checksum (format_version 2 on): a mismatch raises
        ``ImageChecksumError`` naming the camera, row and side.
        """
        return (
            self.image_bytes(camera_serial, row, "left"),
            self.image_bytes(camera_serial, row, "right"),
        )

    @_guarded("an image")
    def image_bytes(self, camera_serial: int, row: int, side: str) -> bytes:
        """One encoded image (``side`` "left" or "right"), checked as ``frame_bytes`` does."""
        view = self._views.get(camera_serial)
        if view is None:
            view = self._views[camera_serial] = _BlobView(
                self._group(camera_serial), self.frame_count(camera_serial), self.info.has_checksums
            )
        n = view.offsets.shape[0]
        if not 0 <= row < n:
            raise FrameRowError(f"camera {camera_serial} has frames 0..{n - 1}, not {row}")
        k = SIDES.index(side)
        start, length = int(view.offsets[row, k]), int(view.lengths[row, k])
        if start < 0 or start + length > view.sizes[k]:
            raise SessionFormatError(
                f"{self._path}: camera {camera_serial} frame {row} {side} bytes "
                f"[{start}, {start + length}) lie past the end of {side}_bytes "
                f"({view.sizes[k]}); the file is damaged, run verify() for a full report"
            )
        data = view.read(k, start, length)
        if view.digests is not None and xxhash.xxh3_64_intdigest(data) != int(view.digests[row, k]):
            raise ImageChecksumError(self._path, camera_serial, row, side)
        return data

    # -- sets, gaps, summary

    @_guarded("the synchronised sets")
    def sets(self) -> SetTable:
        """The synchronised sets whose members are all in the file (see ``SetTable``)."""
        table, keep = self._sets_raw()
        return SetTable(table.set_unix_ns[keep], table.members[keep], table.spread_ns[keep])

    @_guarded("the gap records")
    def gaps(self) -> list[GapRecord]:
        """Drop and gap records, in the order they were written; unknown kinds are skipped."""
        cols = self._gaps_raw()
        out = []
        for i in range(cols["kind"].shape[0]):
            code = int(cols["kind"][i])
            if code not in _GAP_CODES:
                logger.warning("%s: gap record %d has unknown kind %d", self._path, i, code)
                continue
            kind = GapKind(code)
            out.append(
                GapRecord(
                    camera_serial=int(cols["camera_serial"][i]),
                    kind=kind,
                    first_missing_frame_index=int(cols["first_missing_frame_index"][i]),
                    missing_count=int(cols["missing_count"][i]),
                    start_unix_ns=int(cols["start_unix_ns"][i]),
                    end_unix_ns=int(cols["end_unix_ns"][i]),
                )
            )
        return out

    @_guarded("the session events")
    def events(self) -> list[SessionEvent]:
        """The session events (``/events``), in the order they were written; none in a file
        written before the table existed. Unknown kinds are skipped (``verify`` names them)."""
        cols = self.events_raw()
        if cols is None:
            return []
        out = []
        for i in range(cols["kind"].shape[0]):
            code = int(cols["kind"][i])
            if code not in _EVENT_CODES:
                logger.warning("%s: event %d has unknown kind %d", self._path, i, code)
                continue
            out.append(
                SessionEvent(
                    time_unix_ns=int(cols["time_unix_ns"][i]),
                    kind=EventKind(code),
                    node_id=bytes(cols["node_id"][i]).decode("utf-8", "replace"),
                    camera_serial=int(cols["camera_serial"][i]),
                    count=int(cols["count"][i]),
                    detail=bytes(cols["detail"][i]).decode("utf-8", "replace"),
                )
            )
        return out

    def events_raw(self) -> dict[str, np.ndarray] | None:
        """``/events``' columns cut to their common length; None when the file has none."""
        g = self._f.get("events")
        if g is None:
            return None
        for name, dtype in EVENT_COLUMNS.items():
            ds = g[name]
            if (
                ds.ndim != 1
                or ds.dtype != dtype
                or ds.shape[0] * dtype.itemsize > self._size_bytes  # a damaged shape
            ):
                raise ValueError(f"events/{name} has shape {ds.shape} and type {ds.dtype}")
        n = min(g[name].shape[0] for name in EVENT_COLUMNS)
        return {name: g[name][:n] for name in EVENT_COLUMNS}

    @_guarded("/summary")
    def summary(self) -> dict[str, Any]:
        """Per-camera totals written by a clean close: ``{serial: {frames, ...}}`` plus "extra".

        Empty when the file was not closed cleanly.
        """
        if not self.info.closed_cleanly:
            return {}
        s = self._f["summary"]
        serials = [int(x) for x in s["camera_serial"][:]]
        columns = {name: s[name][:] for name in SUMMARY_COLUMNS}
        out: dict[str, Any] = {
            str(serial): {name: int(columns[name][i]) for name in SUMMARY_COLUMNS}
            for i, serial in enumerate(serials)
        }
        # computed from /sets as the stop summary and 'egosurg session info' compute it
        for serial, n in missing_in_sets(self.sets().members, self.info.camera_serials).items():
            if str(serial) in out:
                out[str(serial)]["missing_in_sets"] = n
        out["extra"] = json.loads(_str_attr(s.attrs, "summary_json", "{}"))
        return out

    @_guarded("it to verify it")
    def verify(self, *, check_images: bool = True) -> list[str]:
        """Integrity problems, each a line starting "error:" or "note:"; empty means OK.

        A note is what a writer that was killed or is still writing leaves (unequal table
        lengths, sets ahead of their frames); on a cleanly closed file the same is an error.
        ``check_images`` reads every image: its checksum (format_version 2 on) and JPEG markers.
        See ``protocol.session.verify``.
        """
        return verify_session(self, check_images=check_images)

    # -- internals

    def _group(self, camera_serial: int) -> h5py.Group:
        if camera_serial not in self.info.camera_serials:
            raise UnknownCameraError(
                f"{self._path}: no camera {camera_serial}; cameras are "
                f"{list(self.info.camera_serials)}"
            )
        return self._f[f"cameras/{camera_serial}"]

    def _sets_raw(self) -> tuple[SetTable, np.ndarray]:
        s = self._f["sets"]
        n = min(s["set_unix_ns"].shape[0], s["members"].shape[0], s["spread_ns"].shape[0])
        members = s["members"][:n]
        counts = np.asarray([self.frame_count(c) for c in self.info.camera_serials])
        keep = np.all((members >= -1) & (members < counts), axis=1) & np.any(members >= 0, axis=1)
        table = SetTable(s["set_unix_ns"][:n], members, s["spread_ns"][:n])
        return table, keep

    def _gaps_raw(self) -> dict[str, np.ndarray]:
        g = self._f["gaps"]
        n = min(g[name].shape[0] for name in GAP_COLUMNS)
        return {name: g[name][:n] for name in GAP_COLUMNS}

    def _read_info(self, version: int) -> SessionInfo:
        a = self._f.attrs
        try:
            serials = tuple(int(s) for s in np.asarray(a["camera_serials"]).reshape(-1))
            if not serials or len(set(serials)) != len(serials):
                raise ValueError(f"camera_serials {list(serials)} is empty or repeats a serial")
            cameras = []
            for serial in serials:
                ga = self._f[f"cameras/{serial}"].attrs
                cameras.append(
                    CameraInfo(
                        camera_serial=int(ga["camera_serial"]),
                        node_id=_str_attr(ga, "node_id"),
                        resolution=_str_attr(ga, "resolution"),
                        width=int(ga["width"]),
                        height=int(ga["height"]),
                        fps_nominal=float(ga["fps_nominal"]),
                        encoding=_str_attr(ga, "encoding"),
                        factory_conf_text=_str_attr(ga, "factory_conf", ""),
                    )
                )
            metadata = json.loads(_str_attr(a, "case_metadata_json", "{}"))
            if not isinstance(metadata, dict) or not all(
                isinstance(v, str) for v in metadata.values()
            ):
                raise ValueError("case_metadata_json is not a JSON object of text values")
            return SessionInfo(
                path=self._path,
                format_version=version,
                session_name=_str_attr(a, "session_name"),
                case_metadata=metadata,
                software_version=_str_attr(a, "software_version", ""),
                rig_config_toml=_str_attr(a, "rig_config_toml", ""),
                tolerance_ns=int(a["tolerance_ns"]),
                started_unix_ns=int(a["started_unix_ns"]),
                stopped_unix_ns=int(a["stopped_unix_ns"]),
                closed_cleanly=bool(int(a["closed_cleanly"])),
                camera_serials=serials,
                cameras=tuple(cameras),
                previous_session_file=_str_attr(a, "previous_session_file", ""),
                take_part=int(a.get("take_part", 1)),
            )
        except READ_ERRORS as exc:
            raise SessionFormatError(
                f"{self._path}: an EgoSurg session (format_version {version}) with a missing or "
                f"bad part: {type(exc).__name__}: {exc}; the file is damaged or was not written "
                "by SessionWriter, re-export it from the recording"
            ) from None

    def _check_layout(self) -> None:
        """Every dataset there, 1-D (members 2-D), of an integer type, and no longer than the
        file can hold: a damaged shape fails here, not as a huge read later."""
        n_cams = len(self.info.camera_serials)
        wanted: list[tuple[str, int, int]] = [  # (name, rank, columns of a 2-D table)
            ("sets/set_unix_ns", 1, 0),
            ("sets/members", 2, n_cams),
            ("sets/spread_ns", 1, 0),
            *((f"gaps/{name}", 1, 0) for name in GAP_COLUMNS),
        ]
        for serial in self.info.camera_serials:
            wanted += [(f"cameras/{serial}/{name}", 1, 0) for name in self.columns]
        for name, rank, columns in wanted:
            try:
                ds = self._f[name]
                if not isinstance(ds, h5py.Dataset):
                    raise TypeError("is not a dataset")
                shape, dtype = ds.shape, ds.dtype
            except READ_ERRORS as exc:
                raise SessionFormatError(
                    f"{self._path}: a session with a missing or bad part: no readable {name} "
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
                    f"{self._path}: {name} has shape {shape} and type {dtype}; a session's is "
                    f"{'(rows,)' if rank == 1 else f'(rows, {columns})'} of integers. The file "
                    "is damaged"
                )
            if shape[0] * dtype.itemsize * max(columns, 1) > self._size_bytes:
                raise SessionFormatError(
                    f"{self._path}: {name} claims {shape[0]} rows, more than a file of "
                    f"{self._size_bytes} bytes can hold; the file is damaged"
                )
        for serial in self.info.camera_serials:
            for side in ("left", "right"):
                name = f"cameras/{serial}/{side}_bytes"
                try:
                    ds = self._f[name]
                    ok = isinstance(ds, h5py.Dataset) and ds.ndim == 1 and ds.dtype.itemsize == 1
                except READ_ERRORS:
                    ok = False
                if not ok:
                    raise SessionFormatError(
                        f"{self._path}: {name} is missing or not a 1-D byte dataset; the file is "
                        "damaged"
                    )


class _BlobView:
    """One camera's image offsets and byte datasets, cached for fast random reads."""

    def __init__(self, group: h5py.Group, rows: int, checksums: bool) -> None:
        self.datasets = (group["left_bytes"], group["right_bytes"])
        # the stored XXH3-64 of each image as uint64, or None in a file from before checksums
        self.digests: np.ndarray | None = None
        if checksums:
            digests = [group["left_xxh3_64"][:rows], group["right_xxh3_64"][:rows]]
            self.digests = np.stack(digests, axis=1).astype(np.uint64)
        self.sizes = tuple(int(ds.shape[0]) for ds in self.datasets)
        self.offsets = np.stack(
            [group["left_offset"][:rows], group["right_offset"][:rows]], axis=1
        ).astype(np.int64)
        self.lengths = np.stack(
            [group["left_length"][:rows], group["right_length"][:rows]], axis=1
        ).astype(np.int64)

    def read(self, side: int, start: int, length: int) -> bytes:
        buf = np.empty(length, dtype=np.uint8)
        if length:  # the low-level read skips h5py's slicing machinery, 10x faster here
            dsid = self.datasets[side].id
            fspace = dsid.get_space()
            fspace.select_hyperslab((start,), (length,))
            dsid.read(h5py.h5s.create_simple((length,)), fspace, buf)
        return buf.tobytes()


_GAP_CODES = frozenset(int(k) for k in GapKind)
_EVENT_CODES = frozenset(int(k) for k in EventKind)


def _str_attr(attrs: Any, name: str, default: str | None = None) -> str:
    if default is not None and name not in attrs:
        return default
    value = attrs[name]
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if not isinstance(value, str):
        raise TypeError(f"attribute {name!r} is {type(value).__name__}, not a string")
    return value


def _open_session(path: Path, allow_truncated: bool = False) -> tuple[h5py.File, int]:
    """The open file and its format_version; see ``protocol.session.open`` for the order."""
    if not path.exists():
        raise SessionNotFoundError(
            f"{path}: no such session file; check the path (sessions are named "
            "<session_name>.h5 in the recorder's output directory)"
        )
    if path.is_dir():
        raise SessionFormatError(
            f"{path}: a directory, not an EgoSurg session; pass the .h5 file the recorder wrote"
        )
    try:
        if allow_truncated:
            read_superblock(path)
        else:  # before HDF5 sees it: SWMR reading skips HDF5's own check
            check_superblock(path)
    except PermissionError:
        raise SessionFormatError(
            f"{path}: no permission to read it (session files are owner-only, mode 0600); run "
            "as the recorder's user"
        ) from None
    except OSError as exc:
        raise SessionFormatError(f"{path}: cannot read it: {exc}") from None
    f = open_hdf5(path, cache_bytes=READ_CACHE_BYTES, cache_slots=10007)
    try:
        try:
            fmt = f.attrs.get("format")
        except READ_ERRORS as exc:
            raise SessionFormatError(
                f"{path}: HDF5 cannot read its root attributes ({exc}); the file is damaged"
            ) from None
        if isinstance(fmt, bytes):
            fmt = fmt.decode("utf-8", "replace")
        if fmt != FORMAT:
            raise SessionFormatError(
                f"{path}: an HDF5 file but not an EgoSurg session (root attribute format is "
                f"{fmt!r}, expected {FORMAT!r}); pass the .h5 file the recorder wrote"
            )
        try:
            version = int(f.attrs["format_version"])
        except READ_ERRORS:
            raise SessionFormatError(
                f"{path}: an EgoSurg session without a valid format_version; the file is "
                "damaged, copy it again from the recorder"
            ) from None
        if version > FORMAT_VERSION:
            raise SessionFormatError(
                f"{path}: session format_version {version} was written by a newer EgoSurg; "
                f"this one reads up to version {FORMAT_VERSION}. Upgrade egosurg."
            )
        if version < OLDEST_FORMAT_VERSION:
            raise SessionFormatError(f"{path}: invalid session format_version {version}")
    except BaseException:
        f.close()
        raise
    return f, version
