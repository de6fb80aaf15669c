"""The session file: one HDF5 file per recording, written while it records (SWMR).

``SessionWriter`` is used by the recorder; ``SessionReader`` by the session tools, calibration and
the reconstructor. The full layout, written so anyone can read a session with plain h5py or
``h5dump``, is in ``docs/session.md``; in short::

    /                 attrs: format="egosurg-session", format_version=1, session_name, ...
    /cameras/<serial> attrs: the CameraInfo fields; 1-D tables, one row per frame:
                      capture_unix_ns, host_receive_unix_ns, recorder_receive_unix_ns,
                      frame_index, seq, ptp_offset_ns, ptp_locked,
                      left_offset, left_length, right_offset, right_length
                      and the encoded images as received, end to end in left_bytes / right_bytes
    /sets             set_unix_ns (N,), members (N, C) row per camera or -1, spread_ns (N,)
    /gaps             camera_serial, kind, first_missing_frame_index, missing_count,
                      start_unix_ns, end_unix_ns
    /summary          per-camera totals and summary_json, written by a clean close

Crash safety. Every dataset is created before the file switches to SWMR mode, so that a writer
killed at any moment (SIGKILL included) leaves a file that opens without ``h5clear``.
``flush()`` writes and flushes the image bytes before the tables that point into them, and the
frame tables before the sets and gaps that point at frames, so a reader never sees an index past
its data. Rows appended since the last ``flush()`` are held in memory and are lost on a kill.
Tables of a killed writer may differ in length by one flush; the reader uses the consistent
prefix and ``verify()`` notes it.

Speed. Image bytes are appended to an in-memory buffer and written in whole 1 MiB chunks; the
byte datasets grow geometrically (their extent is a capacity; the logical end is the last
offset + length) and are trimmed at a clean close. The small tables are written once per flush.
"""

from __future__ import annotations

import enum
import json
import logging
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

import h5py
import numpy as np

from protocol.errors import UserError

logger = logging.getLogger(__name__)

FORMAT = "egosurg-session"
FORMAT_VERSION = 1
ENCODINGS = ("jpeg", "raw_bgr8")

# Column name -> dtype of the per-camera frame table, in file order.
FRAME_COLUMNS: dict[str, type[np.generic]] = {
    "capture_unix_ns": np.int64,
    "host_receive_unix_ns": np.int64,
    "recorder_receive_unix_ns": np.int64,
    "frame_index": np.int64,
    "seq": np.int64,
    "ptp_offset_ns": np.int64,
    "ptp_locked": np.uint8,
    "left_offset": np.uint64,
    "left_length": np.uint32,
    "right_offset": np.uint64,
    "right_length": np.uint32,
}
GAP_COLUMNS: dict[str, type[np.generic]] = {
    "camera_serial": np.int64,
    "kind": np.uint8,
    "first_missing_frame_index": np.int64,
    "missing_count": np.int64,
    "start_unix_ns": np.int64,
    "end_unix_ns": np.int64,
}
SUMMARY_COLUMNS = ("frames", "missing_frames", "gap_records", "image_bytes")

BLOB_CHUNK_BYTES = 1 << 20  # h5py advises chunks of 10 KiB to 1 MiB
_TABLE_CHUNK_ROWS = 4096  # 32 KiB of int64
_WRITE_BLOCK_BYTES = 4 * BLOB_CHUNK_BYTES
_MIN_BLOB_CAPACITY = 16 * BLOB_CHUNK_BYTES
_MAX_BLOB_GROWTH = 1 << 30
_MAX_PENDING_ROWS = 4096  # a memory bound if the caller forgets to flush()
_MAX_LENGTH = int(np.iinfo(np.uint32).max)
_READ_CACHE_BYTES = 16 * BLOB_CHUNK_BYTES


class SessionFormatError(UserError, ValueError):
    """Not an EgoSurg session, an unsupported format_version, or an inconsistent file."""


class SessionNotFoundError(SessionFormatError, FileNotFoundError):
    """The session file does not exist."""


class SessionWriteError(UserError, OSError):
    """The session file cannot be created or written (it exists, no directory, disk full...)."""


class GapKind(enum.IntEnum):
    """Why frames are missing; the value is the ``kind`` code stored in ``/gaps/kind``."""

    FRAME_INDEX_GAP = 1  # the camera's frame_index skipped: the camera or its SDK dropped frames
    SEQ_GAP = 2  # the publisher's seq skipped: messages lost in transport
    TIME_GAP = 3  # capture_unix_ns jumped by more than 1.5x the median frame interval
    RECONNECT = 4  # the camera reconnected or its agent restarted


@dataclass(frozen=True, kw_only=True)
class CameraInfo:
    """One stereo camera of a recording, as stored in ``/cameras/<serial>`` attributes."""

    camera_serial: int
    node_id: str
    resolution: str
    width: int
    height: int
    fps_nominal: float
    encoding: str
    factory_conf_text: str = ""

    def __post_init__(self) -> None:
        if self.camera_serial < 0:
            raise ValueError(f"camera_serial must be >= 0, got {self.camera_serial}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.camera_serial}: bad size {self.width}x{self.height}")
        if not self.fps_nominal > 0:
            raise ValueError(f"camera {self.camera_serial}: fps_nominal must be > 0")
        if self.encoding not in ENCODINGS:
            raise ValueError(
                f"camera {self.camera_serial}: encoding {self.encoding!r} is not one of {ENCODINGS}"
            )


@dataclass(frozen=True, kw_only=True)
class GapRecord:
    """One row of ``/gaps``. -1 in an integer field means unknown."""

    camera_serial: int
    kind: GapKind
    first_missing_frame_index: int
    missing_count: int
    start_unix_ns: int
    end_unix_ns: int


@dataclass(frozen=True, kw_only=True)
class SessionInfo:
    """The root attributes and camera descriptions of a session file."""

    path: Path
    format_version: int
    session_name: str
    case_metadata: dict[str, str]
    software_version: str
    rig_config_toml: str
    tolerance_ns: int
    started_unix_ns: int
    stopped_unix_ns: int  # 0 unless closed cleanly
    closed_cleanly: bool
    camera_serials: tuple[int, ...]  # the column order of the sets' members
    cameras: tuple[CameraInfo, ...] = field(default=())

    def camera(self, serial: int) -> CameraInfo:
        for cam in self.cameras:
            if cam.camera_serial == serial:
                return cam
        raise KeyError(f"{self.path}: no camera {serial}; cameras are {list(self.camera_serials)}")


class SetTable(NamedTuple):
    """Synchronised sets: ``members[i, c]`` is the frame row of camera c in set i, or -1."""

    set_unix_ns: np.ndarray  # (N,) int64
    members: np.ndarray  # (N, C) int64
    spread_ns: np.ndarray  # (N,) int64


# --------------------------------------------------------------------------------------- writer


class _Blob:
    """An append-only byte dataset written in whole chunks; its extent is a capacity.

    Bytes wait in a reused buffer (fresh memory for every frame costs more in page faults than
    the copy) until whole chunks can be written.
    """

    def __init__(self, ds: h5py.Dataset) -> None:
        self.ds = ds
        self.capacity = 0
        self.logical_end = 0  # bytes appended
        self.written_end = 0  # bytes handed to HDF5; the buffer holds the rest
        self.buffer = np.empty(2 * _WRITE_BLOCK_BYTES, dtype=np.uint8)
        self.fill = 0

    def append(self, data: Any) -> tuple[int, int]:
        src = np.frombuffer(data, dtype=np.uint8)
        n = src.size
        if n > _MAX_LENGTH:
            raise ValueError(f"an image of {n} bytes is larger than the 4 GiB a row can hold")
        if self.fill + n > self.buffer.size:
            self.write(whole_chunks=True)
            if self.fill + n > self.buffer.size:  # a frame larger than the buffer
                bigger = np.empty(_round_up(2 * (self.fill + n), BLOB_CHUNK_BYTES), np.uint8)
                bigger[: self.fill] = self.buffer[: self.fill]
                self.buffer = bigger
        self.buffer[self.fill : self.fill + n] = src
        self.fill += n
        offset = self.logical_end
        self.logical_end += n
        if self.fill >= _WRITE_BLOCK_BYTES:
            self.write(whole_chunks=True)
        return offset, n

    def write(self, *, whole_chunks: bool) -> None:
        n = self.fill
        if whole_chunks:  # keep writes chunk-aligned so HDF5 never reads a chunk back
            n -= (self.written_end + n) % BLOB_CHUNK_BYTES
        if n <= 0:
            return
        end = self.written_end + n
        if end > self.capacity:
            grown = self.capacity + min(max(self.capacity, _MIN_BLOB_CAPACITY), _MAX_BLOB_GROWTH)
            self.capacity = _round_up(max(end, grown), BLOB_CHUNK_BYTES)
            self.ds.resize((self.capacity,))
        self.ds[self.written_end : end] = self.buffer[:n]
        rest = self.fill - n
        self.buffer[:rest] = self.buffer[n : self.fill]
        self.fill = rest
        self.written_end = end


class _CameraWriter:
    def __init__(self, group: h5py.Group, info: CameraInfo) -> None:
        self.info = info
        self.tables = {
            name: _create_table(group, name, dtype) for name, dtype in FRAME_COLUMNS.items()
        }
        self.left = _Blob(_create_blob(group, "left_bytes"))
        self.right = _Blob(_create_blob(group, "right_bytes"))
        self.pending: list[tuple[int, ...]] = []
        self.rows = 0  # appended
        self.rows_in_file = 0
        self.missing_frames = 0
        self.gap_records = 0


class SessionWriter:
    """Writes one session file while it records. Not thread-safe: use it from one thread.

    Call ``flush()`` regularly (the recorder does it a few times a second): what was appended
    before the last ``flush()`` survives a crash, what came after it does not.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        session_name: str,
        case_metadata: Mapping[str, str],
        cameras: Sequence[CameraInfo],
        tolerance_ns: int,
        rig_config_text: str = "",
        software_version: str,
        started_unix_ns: int,
    ) -> None:
        self._path = Path(path)
        serials = [c.camera_serial for c in cameras]
        if not serials:
            raise ValueError("a session needs at least one camera")
        if len(set(serials)) != len(serials):
            raise ValueError(f"camera serials must be unique, got {serials}")
        if not session_name:
            raise ValueError("session_name must not be empty")
        if tolerance_ns <= 0:
            raise ValueError(f"tolerance_ns must be > 0, got {tolerance_ns}")
        bad = {k: v for k, v in case_metadata.items() if not isinstance(v, str)}
        if bad or not all(isinstance(k, str) for k in case_metadata):
            raise ValueError(f"case_metadata must map str to str; bad entries: {bad}")
        if self._path.exists():
            raise SessionWriteError(
                f"{self._path}: already exists; a session file is never overwritten. "
                "Choose another session name or move the old file away."
            )
        if not self._path.parent.is_dir():
            raise SessionWriteError(
                f"{self._path}: directory {self._path.parent} does not exist; create it first"
            )
        self._serials = tuple(serials)
        self._closed = False
        self._sets_pending: list[tuple[int, tuple[int, ...], int]] = []
        self._sets_rows = 0
        self._gaps_pending: list[tuple[int, ...]] = []
        self._gaps_rows = 0
        try:
            # Bounds v110..v110: SWMR needs the 1.10 file format, and pinning the upper bound
            # keeps the file readable by the HDF5 1.10 tools (h5dump) of Debian and JetPack.
            self._f = h5py.File(
                self._path, "x", libver=("v110", "v110"), rdcc_nbytes=8 * BLOB_CHUNK_BYTES
            )
        except OSError as exc:
            raise SessionWriteError(f"{self._path}: cannot create the session file: {exc}") from exc
        try:
            self._cams = self._create_layout(
                session_name=session_name,
                case_metadata=dict(case_metadata),
                cameras=cameras,
                tolerance_ns=tolerance_ns,
                rig_config_text=rig_config_text,
                software_version=software_version,
                started_unix_ns=started_unix_ns,
            )
            self._f.swmr_mode = True
        except BaseException:
            self._f.close()
            self._path.unlink(missing_ok=True)
            raise
        logger.info("session %s: recording to %s", session_name, self._path)

    def _create_layout(
        self,
        *,
        session_name: str,
        case_metadata: dict[str, str],
        cameras: Sequence[CameraInfo],
        tolerance_ns: int,
        rig_config_text: str,
        software_version: str,
        started_unix_ns: int,
    ) -> dict[int, _CameraWriter]:
        f = self._f
        a = f.attrs
        a["format"] = FORMAT
        a["format_version"] = np.int64(FORMAT_VERSION)
        a["session_name"] = session_name
        a["case_metadata_json"] = json.dumps(case_metadata, sort_keys=True)
        a["started_unix_ns"] = np.int64(started_unix_ns)
        a["stopped_unix_ns"] = np.int64(0)
        a["software_version"] = software_version
        a["rig_config_toml"] = rig_config_text
        a["tolerance_ns"] = np.int64(tolerance_ns)
        a["camera_serials"] = np.asarray(self._serials, dtype=np.int64)
        a["closed_cleanly"] = np.uint8(0)
        cams: dict[int, _CameraWriter] = {}
        for info in cameras:
            g = f.create_group(f"cameras/{info.camera_serial}")
            g.attrs["camera_serial"] = np.int64(info.camera_serial)
            g.attrs["node_id"] = info.node_id
            g.attrs["resolution"] = info.resolution
            g.attrs["width"] = np.int64(info.width)
            g.attrs["height"] = np.int64(info.height)
            g.attrs["fps_nominal"] = np.float64(info.fps_nominal)
            g.attrs["encoding"] = info.encoding
            g.attrs["factory_conf"] = info.factory_conf_text
            cams[info.camera_serial] = _CameraWriter(g, info)
        n_cams = len(self._serials)
        sets = f.create_group("sets")
        self._set_time = _create_table(sets, "set_unix_ns", np.int64)
        self._set_members = sets.create_dataset(
            "members",
            shape=(0, n_cams),
            maxshape=(None, n_cams),
            chunks=(max(1, _TABLE_CHUNK_ROWS // n_cams), n_cams),
            dtype=np.int64,
        )
        self._set_spread = _create_table(sets, "spread_ns", np.int64)
        gaps = f.create_group("gaps")
        self._gap_tables = {name: _create_table(gaps, name, dt) for name, dt in GAP_COLUMNS.items()}
        summary = f.create_group("summary")
        summary.create_dataset("camera_serial", data=np.asarray(self._serials, dtype=np.int64))
        for name in SUMMARY_COLUMNS:
            summary.create_dataset(name, shape=(n_cams,), dtype=np.int64, fillvalue=0)
        # SWMR cannot add attributes later, so the one written at close exists from the start.
        summary.attrs["summary_json"] = "{}"
        return cams

    # -- recording

    @property
    def path(self) -> Path:
        return self._path

    @property
    def camera_serials(self) -> tuple[int, ...]:
        return self._serials

    @property
    def bytes_written(self) -> int:
        """Image bytes appended so far, both sides of every camera."""
        return sum(c.left.logical_end + c.right.logical_end for c in self._cams.values())

    def frames_written(self, camera_serial: int) -> int:
        """Frames appended for one camera (including those not yet flushed)."""
        return self._camera(camera_serial).rows

    def append_frame(
        self,
        camera_serial: int,
        *,
        left: Any,
        right: Any,
        capture_unix_ns: int,
        host_receive_unix_ns: int,
        recorder_receive_unix_ns: int,
        frame_index: int,
        seq: int,
        ptp_offset_ns: int,
        ptp_locked: bool,
    ) -> int:
        """Append one stereo frame; ``left``/``right`` are bytes-like and stored as-is.

        Returns the frame's row in ``/cameras/<serial>``, the index that sets refer to.
        """
        cam = self._camera(camera_serial)
        lo, ll = cam.left.append(left)
        ro, rl = cam.right.append(right)
        cam.pending.append(
            (
                capture_unix_ns,
                host_receive_unix_ns,
                recorder_receive_unix_ns,
                frame_index,
                seq,
                ptp_offset_ns,
                1 if ptp_locked else 0,
                lo,
                ll,
                ro,
                rl,
            )
        )
        row = cam.rows
        cam.rows += 1
        if len(cam.pending) >= _MAX_PENDING_ROWS:
            self.flush()
        return row

    def append_set(self, set_unix_ns: int, members: Sequence[int], spread_ns: int) -> int:
        """Append a synchronised set; ``members`` has one frame row per camera, -1 if missing.

        The columns follow ``camera_serials``. Returns the set's row.
        """
        self._check_open()
        row = tuple(int(m) for m in members)
        if len(row) != len(self._serials):
            raise ValueError(
                f"a set needs {len(self._serials)} members (one per camera), got {len(row)}"
            )
        if all(m == -1 for m in row):
            raise ValueError("a set needs at least one member")
        for serial, m in zip(self._serials, row, strict=True):
            if m < -1 or m >= self._cams[serial].rows:
                raise ValueError(
                    f"set member {m} of camera {serial} is not a frame row "
                    f"(0..{self._cams[serial].rows - 1}) nor -1"
                )
        self._sets_pending.append((int(set_unix_ns), row, int(spread_ns)))
        self._sets_rows += 1
        if len(self._sets_pending) >= _MAX_PENDING_ROWS:
            self.flush()
        return self._sets_rows - 1

    def append_gap(
        self,
        camera_serial: int,
        *,
        kind: GapKind | int,
        first_missing_frame_index: int,
        missing_count: int,
        start_unix_ns: int,
        end_unix_ns: int,
    ) -> int:
        """Append a drop or gap record (-1 for a field that is not known). Returns its row."""
        cam = self._camera(camera_serial)
        code = GapKind(kind)
        self._gaps_pending.append(
            (
                camera_serial,
                int(code),
                first_missing_frame_index,
                missing_count,
                start_unix_ns,
                end_unix_ns,
            )
        )
        cam.gap_records += 1
        if code in (GapKind.FRAME_INDEX_GAP, GapKind.SEQ_GAP) and missing_count > 0:
            cam.missing_frames += missing_count
        self._gaps_rows += 1
        if len(self._gaps_pending) >= _MAX_PENDING_ROWS:
            self.flush()
        return self._gaps_rows - 1

    def flush(self, *, fsync: bool = False) -> None:
        """Make everything appended so far durable against a crash of this process.

        Order: image bytes, then the frame tables that point into them, then sets and gaps that
        point at frames. ``fsync=True`` also asks the OS to put it on disk (power loss).
        """
        self._check_open()
        try:
            self._flush()
            if fsync:
                os.fsync(self._f.id.get_vfd_handle())
        except OSError as exc:
            raise SessionWriteError(
                f"{self._path}: writing failed ({exc}); check free disk space and the disk"
            ) from exc

    def _flush(self) -> None:
        cams = self._cams.values()
        for cam in cams:
            for blob in (cam.left, cam.right):
                blob.write(whole_chunks=False)
                blob.ds.flush()
        for cam in cams:
            if cam.pending:
                columns = list(zip(*cam.pending, strict=True))
                start, end = cam.rows_in_file, cam.rows_in_file + len(cam.pending)
                for (name, dtype), col in zip(FRAME_COLUMNS.items(), columns, strict=True):
                    _append_rows(cam.tables[name], start, end, np.asarray(col, dtype=dtype))
                cam.pending.clear()
                cam.rows_in_file = end
            for ds in cam.tables.values():
                ds.flush()
        if self._sets_pending:
            start = self._set_time.shape[0]
            end = start + len(self._sets_pending)
            times, members, spreads = zip(*self._sets_pending, strict=True)
            _append_rows(self._set_members, start, end, np.asarray(members, dtype=np.int64))
            _append_rows(self._set_spread, start, end, np.asarray(spreads, dtype=np.int64))
            _append_rows(self._set_time, start, end, np.asarray(times, dtype=np.int64))
            self._sets_pending.clear()
        for ds in (self._set_members, self._set_spread, self._set_time):
            ds.flush()
        if self._gaps_pending:
            start = self._gap_tables["kind"].shape[0]
            end = start + len(self._gaps_pending)
            columns = list(zip(*self._gaps_pending, strict=True))
            for (name, dtype), col in zip(GAP_COLUMNS.items(), columns, strict=True):
                _append_rows(self._gap_tables[name], start, end, np.asarray(col, dtype=dtype))
            self._gaps_pending.clear()
        for ds in self._gap_tables.values():
            ds.flush()

    def close(self, stopped_unix_ns: int, summary: Mapping[str, Any] | None = None) -> None:
        """Flush, write ``/summary`` (plus ``summary`` as JSON) and mark the file closed cleanly."""
        self._check_open()
        # numpy scalars are welcome in the summary; anything else must be JSON already
        extra = json.dumps(
            dict(summary or {}), sort_keys=True, default=lambda o: np.asarray(o).tolist()
        )
        try:
            self._flush()
            for cam in self._cams.values():
                for blob in (cam.left, cam.right):
                    blob.ds.resize((blob.logical_end,))
                    blob.ds.flush()
            s = self._f["summary"]
            cams = [self._cams[serial] for serial in self._serials]
            s["frames"][:] = [c.rows for c in cams]
            s["missing_frames"][:] = [c.missing_frames for c in cams]
            s["gap_records"][:] = [c.gap_records for c in cams]
            s["image_bytes"][:] = [c.left.logical_end + c.right.logical_end for c in cams]
            s.attrs.modify("summary_json", extra)
            self._f.attrs.modify("stopped_unix_ns", np.int64(stopped_unix_ns))
            self._f.flush()
            self._f.attrs.modify("closed_cleanly", np.uint8(1))
            self._f.flush()
        except OSError as exc:
            raise SessionWriteError(
                f"{self._path}: closing failed ({exc}); the data up to the last flush is "
                "readable; check free disk space"
            ) from exc
        finally:
            self._closed = True
            self._f.close()
        logger.info("session file %s closed cleanly", self._path)

    def abort(self) -> None:
        """Flush what can be flushed and close without marking the file closed cleanly."""
        if self._closed:
            return
        try:
            self._flush()
        except Exception:
            logger.exception("session file %s: final flush failed", self._path)
        finally:
            self._closed = True
            self._f.close()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._closed:
            return
        if exc_type is None:
            self.close(time.time_ns())
        else:
            self.abort()

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self._path}: the session writer is closed")

    def _camera(self, serial: int) -> _CameraWriter:
        self._check_open()
        try:
            return self._cams[serial]
        except KeyError:
            raise ValueError(
                f"camera {serial} is not in this session; cameras are {list(self._serials)}"
            ) from None


def _round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def _create_table(group: h5py.Group, name: str, dtype: type[np.generic]) -> h5py.Dataset:
    return group.create_dataset(
        name, shape=(0,), maxshape=(None,), chunks=(_TABLE_CHUNK_ROWS,), dtype=dtype
    )


def _create_blob(group: h5py.Group, name: str) -> h5py.Dataset:
    return group.create_dataset(
        name, shape=(0,), maxshape=(None,), chunks=(BLOB_CHUNK_BYTES,), dtype=np.uint8
    )


def _append_rows(ds: h5py.Dataset, start: int, end: int, values: np.ndarray) -> None:
    ds.resize(end, axis=0)
    ds[start:end] = values


# --------------------------------------------------------------------------------------- reader


class SessionReader:
    """Reads a session file: finished, being written, or left by a killed writer.

    Everything it returns is the consistent prefix: a frame table is as long as the shortest of
    its columns, and sets whose members are not all in the file are left out (``verify()``
    says so). Use it as a context manager. ``refresh()`` picks up rows a live writer flushed.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._path = Path(path)
        self._f = _open_session(self._path)
        try:
            self.info = self._read_info()
        except BaseException:
            self._f.close()
            raise
        self._views: dict[int, _BlobView] = {}

    @property
    def path(self) -> Path:
        return self._path

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> SessionReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def refresh(self) -> None:
        """See rows flushed by a live writer since opening (root attributes are not refreshed)."""
        if self._f.swmr_mode:

            def visit(_name: str, obj: object) -> None:
                if isinstance(obj, h5py.Dataset):
                    obj.refresh()

            self._f.visititems(visit)
        self._views.clear()

    # -- frames

    def frame_count(self, camera_serial: int) -> int:
        g = self._group(camera_serial)
        return min(g[name].shape[0] for name in FRAME_COLUMNS)

    def frame_table(self, camera_serial: int) -> dict[str, np.ndarray]:
        """Every column of ``FRAME_COLUMNS`` for one camera, as numpy arrays of equal length."""
        g = self._group(camera_serial)
        n = self.frame_count(camera_serial)
        return {name: g[name][:n] for name in FRAME_COLUMNS}

    def frame_bytes(self, camera_serial: int, row: int) -> tuple[bytes, bytes]:
        """The (left, right) encoded images of one frame, exactly as they were received."""
        view = self._views.get(camera_serial)
        if view is None:
            view = self._views[camera_serial] = _BlobView(
                self._group(camera_serial), self.frame_count(camera_serial)
            )
        n = view.offsets.shape[0]
        if not 0 <= row < n:
            raise IndexError(f"camera {camera_serial} has frames 0..{n - 1}, not {row}")
        out = []
        for side in (0, 1):
            start = int(view.offsets[row, side])
            length = int(view.lengths[row, side])
            if start < 0 or start + length > view.sizes[side]:
                name = ("left", "right")[side]
                raise SessionFormatError(
                    f"{self._path}: camera {camera_serial} frame {row} {name} bytes "
                    f"[{start}, {start + length}) lie past the end of {name}_bytes "
                    f"({view.sizes[side]}); the file is damaged, run verify() for a full report"
                )
            out.append(view.read(side, start, length))
        return out[0], out[1]

    # -- sets, gaps, summary

    def sets(self) -> SetTable:
        """The synchronised sets whose members are all in the file (see ``SetTable``)."""
        table, keep = self._sets_raw()
        return SetTable(table.set_unix_ns[keep], table.members[keep], table.spread_ns[keep])

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
        out["extra"] = json.loads(_str_attr(s.attrs, "summary_json", "{}"))
        return out

    def verify(self, *, check_images: bool = True) -> list[str]:
        """Integrity problems, each a line starting "error:" or "note:"; empty means OK.

        A note is what a writer that was killed or is still writing leaves (unequal table
        lengths, sets ahead of their frames); on a cleanly closed file the same is an error.
        ``check_images`` reads every image's first and last bytes (the whole byte datasets).
        """
        clean = self.info.closed_cleanly
        # What a killed or live writer leaves behind is expected there, and damage otherwise.
        tail = "error" if clean else "note"
        problems = []
        if not clean:
            problems.append(
                "note: not closed cleanly (the writer was killed or is still writing); "
                "everything up to its last flush() is readable"
            )
        groups = set(self._f["cameras"].keys())
        expected = {str(s) for s in self.info.camera_serials}
        if groups != expected:
            problems.append(
                f"error: /cameras holds {sorted(groups)} but camera_serials is {sorted(expected)}"
            )
        for serial in self.info.camera_serials:
            problems += self._verify_camera(serial, tail, check_images)
        problems += self._verify_sets(tail)
        problems += self._verify_gaps(tail)
        if clean:
            problems += self._verify_summary()
        return problems

    def _verify_camera(self, serial: int, tail: str, check_images: bool) -> list[str]:
        out = []
        g = self._group(serial)
        info = self.info.camera(serial)
        lengths = [g[name].shape[0] for name in FRAME_COLUMNS]
        t = self.frame_table(serial)
        if len(set(lengths)) > 1:
            out.append(
                f"{tail}: camera {serial}: frame table columns have {min(lengths)} to "
                f"{max(lengths)} rows; using the first {min(lengths)}"
            )
        cap = t["capture_unix_ns"]
        bad = np.flatnonzero(np.diff(cap) <= 0) + 1
        if bad.size:
            out.append(
                f"error: camera {serial}: capture_unix_ns does not increase at rows {_rows(bad)}"
            )
        for side in ("left", "right"):
            ds = g[f"{side}_bytes"]
            size = np.uint64(ds.shape[0])
            off = t[f"{side}_offset"].astype(np.uint64)
            length = t[f"{side}_length"].astype(np.uint64)
            room = np.where(off <= size, size - np.minimum(off, size), np.uint64(0))
            outside = (off > size) | (length > room)
            if outside.any():
                rows = _rows(np.flatnonzero(outside))
                out.append(
                    f"error: camera {serial}: {side} bytes of rows {rows} "
                    f"lie past the end of {side}_bytes ({int(size)} bytes)"
                )
            inside = np.flatnonzero(~outside)
            off_in = off[inside].astype(np.int64)
            len_in = length[inside].astype(np.int64)
            overlap = np.flatnonzero(off_in[1:] < off_in[:-1] + len_in[:-1]) + 1
            if overlap.size:
                out.append(
                    f"error: camera {serial}: {side} bytes of rows {_rows(inside[overlap])} "
                    "overlap the previous frame's"
                )
            if info.encoding == "raw_bgr8":
                wrong = np.flatnonzero(len_in != info.width * info.height * 3)
                if wrong.size:
                    out.append(
                        f"error: camera {serial}: {side} raw_bgr8 images of rows "
                        f"{_rows(inside[wrong])} are not {info.width}x{info.height}x3 bytes"
                    )
            elif check_images:
                wrong = np.flatnonzero(_bad_jpeg(ds, off_in, len_in))
                if wrong.size:
                    out.append(
                        f"error: camera {serial}: {side} images of rows {_rows(inside[wrong])} "
                        "are not JPEG (must start with FF D8 and end with FF D9)"
                    )
        return out

    def _verify_sets(self, tail: str) -> list[str]:
        out = []
        s = self._f["sets"]
        lengths = [s[name].shape[0] for name in ("set_unix_ns", "members", "spread_ns")]
        if len(set(lengths)) > 1:
            out.append(
                f"{tail}: sets: columns have {min(lengths)} to {max(lengths)} rows; "
                f"using the first {min(lengths)}"
            )
        n_cams = len(self.info.camera_serials)
        if s["members"].ndim != 2 or s["members"].shape[1] != n_cams:
            return [*out, f"error: sets/members has shape {s['members'].shape}, not (N, {n_cams})"]
        table, keep = self._sets_raw()
        members = table.members
        counts = np.asarray([self.frame_count(c) for c in self.info.camera_serials])
        invalid = np.flatnonzero(np.any(members < -1, axis=1) | np.all(members == -1, axis=1))
        if invalid.size:
            out.append(f"error: sets {_rows(invalid)} have members that are neither rows nor -1")
        ahead = np.flatnonzero(np.any(members >= counts, axis=1))
        if ahead.size:
            out.append(
                f"{tail}: sets {_rows(ahead)} have members past the end of a camera's frame "
                "table; they are left out"
            )
        kept = np.flatnonzero(keep)
        members = members[kept]
        if members.shape[0] == 0:
            return out
        times = np.empty(members.shape, dtype=np.int64)
        for c, serial in enumerate(self.info.camera_serials):
            cap = self.frame_table(serial)["capture_unix_ns"]
            col = members[:, c]
            times[:, c] = np.where(col >= 0, cap[np.maximum(col, 0)] if cap.size else 0, 0)
        present = members >= 0
        big = np.iinfo(np.int64).max
        t_max = np.where(present, times, -big).max(axis=1)
        t_min = np.where(present, times, big).min(axis=1)
        wrong = np.flatnonzero(table.spread_ns[kept] != t_max - t_min)
        if wrong.size:
            out.append(
                f"error: sets {_rows(kept[wrong])}: spread_ns is not the max - min "
                "capture_unix_ns of their members"
            )
        back = np.flatnonzero(np.diff(table.set_unix_ns[kept]) < 0) + 1
        if back.size:
            out.append(f"error: set_unix_ns decreases at sets {_rows(kept[back])}")
        for c, serial in enumerate(self.info.camera_serials):
            sets_with = np.flatnonzero(present[:, c])
            reused = np.flatnonzero(np.diff(members[sets_with, c]) <= 0) + 1
            if reused.size:
                out.append(
                    f"error: camera {serial}: sets {_rows(kept[sets_with[reused]])} reuse a frame "
                    "or go back in time"
                )
        return out

    def _verify_gaps(self, tail: str) -> list[str]:
        out = []
        g = self._f["gaps"]
        lengths = [g[name].shape[0] for name in GAP_COLUMNS]
        if len(set(lengths)) > 1:
            out.append(
                f"{tail}: gaps: columns have {min(lengths)} to {max(lengths)} rows; "
                f"using the first {min(lengths)}"
            )
        cols = self._gaps_raw()
        unknown = np.flatnonzero(~np.isin(cols["kind"], [int(k) for k in GapKind]))
        if unknown.size:
            out.append(f"error: gap records {_rows(unknown)} have an unknown kind")
        strangers = np.flatnonzero(~np.isin(cols["camera_serial"], self.info.camera_serials))
        if strangers.size:
            out.append(f"error: gap records {_rows(strangers)} name a camera not in the session")
        backwards = np.flatnonzero(cols["end_unix_ns"] < cols["start_unix_ns"])
        if backwards.size:
            out.append(f"error: gap records {_rows(backwards)} end before they start")
        return out

    def _verify_summary(self) -> list[str]:
        out = []
        summary = self.summary()
        gap_serials = self._gaps_raw()["camera_serial"]
        for serial in self.info.camera_serials:
            totals = summary.get(str(serial))
            if totals is None:
                out.append(f"error: /summary has no totals for camera {serial}")
                continue
            if totals["frames"] != self.frame_count(serial):
                out.append(
                    f"error: camera {serial}: /summary counts {totals['frames']} frames, the "
                    f"table holds {self.frame_count(serial)}"
                )
            if totals["gap_records"] != int(np.count_nonzero(gap_serials == serial)):
                out.append(f"error: camera {serial}: /summary gap_records disagrees with /gaps")
        return out

    # -- internals

    def _group(self, camera_serial: int) -> h5py.Group:
        if camera_serial not in self.info.camera_serials:
            raise KeyError(
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

    def _read_info(self) -> SessionInfo:
        a = self._f.attrs
        try:
            serials = tuple(int(s) for s in np.asarray(a["camera_serials"]).reshape(-1))
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
            for name in ("sets/set_unix_ns", "sets/members", "sets/spread_ns"):
                self._f[name]
            for name in GAP_COLUMNS:
                self._f[f"gaps/{name}"]
            for serial in serials:
                for name in (*FRAME_COLUMNS, "left_bytes", "right_bytes"):
                    self._f[f"cameras/{serial}/{name}"]
            return SessionInfo(
                path=self._path,
                format_version=int(a["format_version"]),
                session_name=_str_attr(a, "session_name"),
                case_metadata=json.loads(_str_attr(a, "case_metadata_json", "{}")),
                software_version=_str_attr(a, "software_version", ""),
                rig_config_toml=_str_attr(a, "rig_config_toml", ""),
                tolerance_ns=int(a["tolerance_ns"]),
                started_unix_ns=int(a["started_unix_ns"]),
                stopped_unix_ns=int(a["stopped_unix_ns"]),
                closed_cleanly=bool(int(a["closed_cleanly"])),
                camera_serials=serials,
                cameras=tuple(cameras),
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise SessionFormatError(
                f"{self._path}: an EgoSurg session (format_version {FORMAT_VERSION}) with a "
                f"missing or bad part: {exc}; the file is damaged or was not written by "
                "SessionWriter, re-export it from the recording"
            ) from None


class _BlobView:
    """One camera's image offsets and byte datasets, cached for fast random reads."""

    def __init__(self, group: h5py.Group, rows: int) -> None:
        self.datasets = (group["left_bytes"], group["right_bytes"])
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


def _rows(indices: np.ndarray, limit: int = 5) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    more = indices.size - limit
    return f"{shown} and {more} more" if more > 0 else shown


def _bad_jpeg(ds: h5py.Dataset, offsets: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Which images lack the JPEG start (FF D8) or end (FF D9) marker; reads in 16 MiB blocks."""
    bad = lengths < 4
    ok = ~bad
    off, end = offsets[ok], offsets[ok] + lengths[ok]
    pos = np.concatenate([off, off + 1, end - 2, end - 1])
    order = np.argsort(pos, kind="stable")
    sorted_pos = pos[order]
    values = np.empty(pos.size, dtype=np.uint8)
    i = 0
    while i < sorted_pos.size:
        start = int(sorted_pos[i]) - int(sorted_pos[i]) % BLOB_CHUNK_BYTES
        stop = min(start + 16 * BLOB_CHUNK_BYTES, ds.shape[0])
        j = int(np.searchsorted(sorted_pos, stop, side="left"))
        block = ds[start:stop]
        values[order[i:j]] = block[sorted_pos[i:j] - start]
        i = j
    v = values.reshape(4, -1)
    bad[ok] = ~((v[0] == 0xFF) & (v[1] == 0xD8) & (v[2] == 0xFF) & (v[3] == 0xD9))
    return bad


def _str_attr(attrs: Any, name: str, default: str | None = None) -> str:
    if default is not None and name not in attrs:
        return default
    value = attrs[name]
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if not isinstance(value, str):
        raise TypeError(f"attribute {name!r} is {type(value).__name__}, not a string")
    return value


def _open_session(path: Path) -> h5py.File:
    if not path.exists():
        raise SessionNotFoundError(
            f"{path}: no such session file; check the path (sessions are named "
            "<session_name>.h5 in the recorder's output directory)"
        )
    if path.is_dir() or not h5py.is_hdf5(path):
        raise SessionFormatError(
            f"{path}: not an HDF5 file, so not an EgoSurg session; pass the .h5 file the "
            "recorder wrote"
        )
    try:
        # swmr=True also opens files of live or killed writers; the cache holds a few chunks
        f = h5py.File(path, "r", swmr=True, rdcc_nbytes=_READ_CACHE_BYTES, rdcc_nslots=10007)
    except OSError:
        try:
            f = h5py.File(path, "r")  # an HDF5 file older than the 1.10 format
        except OSError as exc:
            raise SessionFormatError(
                f"{path}: HDF5 cannot open it ({exc}); copy it again from the recorder"
            ) from None
    try:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode("utf-8", "replace")
        if fmt != FORMAT:
            raise SessionFormatError(
                f"{path}: an HDF5 file but not an EgoSurg session (root attribute format is "
                f"{fmt!r}, expected {FORMAT!r}); pass the .h5 file the recorder wrote"
            )
        try:
            version = int(f.attrs["format_version"])
        except (KeyError, ValueError, TypeError):
            raise SessionFormatError(
                f"{path}: an EgoSurg session without a valid format_version; the file is "
                "damaged, copy it again from the recorder"
            ) from None
        if version > FORMAT_VERSION:
            raise SessionFormatError(
                f"{path}: session format_version {version} was written by a newer EgoSurg; "
                f"this one reads up to version {FORMAT_VERSION}. Upgrade egosurg."
            )
        if version < 1:
            raise SessionFormatError(f"{path}: invalid session format_version {version}")
    except BaseException:
        f.close()
        raise
    return f
