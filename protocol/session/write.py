"""Writing a session file while it records (SWMR): ``SessionWriter``, used by the recorder.

See ``protocol.session`` for the overview and crash-safety rules, ``docs/session.md`` for the
layout.

Speed. The image bytes are the load (about 70 MB/s on the reference rig, many times that when a
recorder catches up): each camera side's bytes are gathered into whole chunks, which a
``ChunkSink`` writes at their place in the file from a thread of its own, with direct I/O where
the file system allows it (``protocol.session.chunk_sink`` says why and what it measured).
HDF5 keeps the layout: the byte datasets allocate their chunks as they grow (their extent is a
capacity;
the logical end is the last offset + length) and are trimmed at a clean close. The file is
opened without a chunk cache (``rdcc_nbytes=0``): the tables' chunks are only appended to, so a
cache would only add a copy. The small tables are written once per flush.

The datasets themselves (the chunk-writing byte blobs, a camera's tables, the low-level row
appends) live in ``protocol.session.datasets``; this module owns the file, its layout and the
``SessionWriter`` API.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from protocol.sealing import Recipient
from protocol.session.chunk_sink import ChunkSink
from protocol.session.datasets import (
    CameraWriter,
    append_rows,
    append_table_rows,
    create_table,
)
from protocol.session.format import (
    BLOB_CHUNK_BYTES,
    EVENT_COLUMNS,
    EVENT_DETAIL_BYTES,
    EVENT_NODE_ID_BYTES,
    FORMAT,
    FORMAT_VERSION,
    FRAME_COLUMNS,
    GAP_COLUMNS,
    SEALED_FORMAT_VERSION,
    SEALED_FRAME_COLUMNS,
    SUMMARY_COLUMNS,
    TABLE_CHUNK_ROWS,
    CameraInfo,
    EventKind,
    GapKind,
    SessionWriteError,
    event_text,
)
from protocol.session.new_file import check_arguments, check_new_file, create_file
from protocol.session.privacy import redact_secrets
from protocol.session.sealed import StoredSeal, WriterSeal

logger = logging.getLogger(__name__)

_MAX_PENDING_ROWS = 4096  # a memory bound if the caller forgets to flush()


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
        blob_chunk_bytes: int = BLOB_CHUNK_BYTES,
        direct_io: bool | None = None,
        previous_session_file: str = "",
        take_part: int = 1,
        recipients: Sequence[Recipient] = (),
        sealed_copy: StoredSeal | None = None,
    ) -> None:
        """``recipients``: seal the session for them (``protocol.session.sealed``): each image,
        metadata value and the rig text is stored sealed under a fresh data key that only they
        can unwrap; none writes a plaintext session. ``sealed_copy``: a sealed session's
        sealing as stored, for ``recover`` (its metadata and rig text replace the arguments,
        and images are appended sealed already, ``append_sealed_frame``).
        ``direct_io``: write the image chunks past the page cache (``O_DIRECT``); None does
        where the file system allows it (see ``protocol.session.chunk_sink``).
        ``previous_session_file`` and ``take_part``: a take resumed after the recorder was killed
        links its new file to the previous part (its file name, same folder).
        ``rig_config_text`` is stored without any key material (``protocol.session.privacy``);
        the file is created with mode 0600."""
        self._path = Path(path)
        serials = [c.camera_serial for c in cameras]
        check_arguments(
            serials,
            session_name=session_name,
            case_metadata=case_metadata,
            tolerance_ns=tolerance_ns,
            blob_chunk_bytes=blob_chunk_bytes,
            previous_session_file=previous_session_file,
            take_part=take_part,
        )
        if recipients and sealed_copy is not None:
            raise ValueError("recipients seal a new session, sealed_copy copies one: not both")
        rig_text = redact_secrets(rig_config_text)
        self._seal: WriterSeal | None = None
        if recipients:
            self._seal = WriterSeal.new(recipients, case_metadata, rig_text)
        elif sealed_copy is not None:
            self._seal = WriterSeal(None, sealed_copy)
        check_new_file(self._path)
        self._serials = tuple(serials)
        self._closed = False
        self._write_error: OSError | None = None  # of the last flush, until one succeeds
        self._sets_pending: list[tuple[int, tuple[int, ...], int]] = []
        self._sets_rows = 0
        self._gaps_pending: list[tuple[int, ...]] = []
        self._gaps_rows = 0
        self._events_pending: list[tuple[int, int, bytes, int, int, bytes]] = []
        self._events_rows = 0
        self._f = create_file(self._path, blob_chunk_bytes)
        try:
            self._sink = ChunkSink(
                self._path, blob_chunk_bytes, direct_io=direct_io, buffers_held=2 * len(serials)
            )
        except BaseException:
            self._f.close()
            self._path.unlink(missing_ok=True)
            raise
        try:
            self._cams = self._create_layout(
                session_name=session_name,
                case_metadata=dict(case_metadata),
                cameras=cameras,
                tolerance_ns=tolerance_ns,
                rig_config_text=rig_text,
                software_version=software_version,
                started_unix_ns=started_unix_ns,
                blob_chunk_bytes=blob_chunk_bytes,
                previous_session_file=previous_session_file,
                take_part=take_part,
            )
            self._f.swmr_mode = True
        except BaseException:
            self._sink.close()
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
        blob_chunk_bytes: int,
        previous_session_file: str,
        take_part: int,
    ) -> dict[int, CameraWriter]:
        f = self._f
        a = f.attrs
        seal = self._seal
        if seal is not None:  # the values as stored: sealed, base64 (docs/session.md)
            case_metadata, rig_config_text = seal.stored.case_metadata, seal.stored.rig_config
            seal.write(f)
        a["format"] = FORMAT
        a["format_version"] = np.int64(FORMAT_VERSION if seal is None else SEALED_FORMAT_VERSION)
        a["session_name"] = session_name
        a["case_metadata_json"] = json.dumps(case_metadata, sort_keys=True)
        a["started_unix_ns"] = np.int64(started_unix_ns)
        a["stopped_unix_ns"] = np.int64(0)
        a["software_version"] = software_version
        a["rig_config_toml"] = rig_config_text
        a["tolerance_ns"] = np.int64(tolerance_ns)
        a["camera_serials"] = np.asarray(self._serials, dtype=np.int64)
        a["closed_cleanly"] = np.uint8(0)
        a["previous_session_file"] = previous_session_file
        a["take_part"] = np.int64(take_part)
        cams: dict[int, CameraWriter] = {}
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
            columns = FRAME_COLUMNS if seal is None else SEALED_FRAME_COLUMNS
            cams[info.camera_serial] = CameraWriter(g, info, blob_chunk_bytes, self._sink, columns)
        n_cams = len(self._serials)
        sets = f.create_group("sets")
        self._set_time = create_table(sets, "set_unix_ns", np.int64)
        self._set_members = sets.create_dataset(
            "members",
            shape=(0, n_cams),
            maxshape=(None, n_cams),
            chunks=(max(1, TABLE_CHUNK_ROWS // n_cams), n_cams),
            dtype=np.int64,
        )
        self._set_spread = create_table(sets, "spread_ns", np.int64)
        gaps = f.create_group("gaps")
        self._gap_tables = {name: create_table(gaps, name, dt) for name, dt in GAP_COLUMNS.items()}
        events = f.create_group("events")
        self._event_tables = {
            name: create_table(events, name, dt) for name, dt in EVENT_COLUMNS.items()
        }
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
    def sealed(self) -> bool:
        """Whether images and case values are stored sealed for recipients."""
        return self._seal is not None

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
        """Append one stereo frame; ``left``/``right`` are bytes-like and stored as-is (in a
        sealed session, sealed for its row, side and capture stamp first).

        Returns the frame's row in ``/cameras/<serial>``, the index that sets refer to.
        """
        cam = self._camera(camera_serial)
        times = (capture_unix_ns, host_receive_unix_ns, recorder_receive_unix_ns)
        counters = (frame_index, seq, ptp_offset_ns, 1 if ptp_locked else 0)
        seal = self._seal
        if seal is None:
            return self._append(cam, left, right, (*times, *counters), cam.rows)
        row = cam.rows

        def store() -> tuple[tuple[int, int, int], tuple[int, int, int]]:
            return seal.store_pair(
                (cam.left, cam.right),
                (left, right),
                camera_serial=camera_serial,
                row=row,
                capture_unix_ns=capture_unix_ns,
            )

        return self._append(cam, None, None, (*times, *counters), row, store)

    def append_sealed_frame(
        self,
        camera_serial: int,
        *,
        left: Any,
        right: Any,
        sealed_row: int,
        capture_unix_ns: int,
        host_receive_unix_ns: int,
        recorder_receive_unix_ns: int,
        frame_index: int,
        seq: int,
        ptp_offset_ns: int,
        ptp_locked: bool,
    ) -> int:
        """Append a frame of a sealed session whose images are sealed already, as stored in
        the session this one copies (``sealed_copy``): ``sealed_row`` is the row their
        associated data names. For ``recover``, which holds no key. Returns the frame's row."""
        cam = self._camera(camera_serial)
        if self._seal is None:
            raise ValueError("append_sealed_frame is for a sealed session; use append_frame")
        times = (capture_unix_ns, host_receive_unix_ns, recorder_receive_unix_ns)
        counters = (frame_index, seq, ptp_offset_ns, 1 if ptp_locked else 0)
        return self._append(cam, left, right, (*times, *counters), sealed_row)

    def _append(
        self,
        cam: CameraWriter,
        left: Any,
        right: Any,
        fields: tuple[int, ...],
        sealed_row: int,
        store: Callable[[], tuple[tuple[int, int, int], tuple[int, int, int]]] | None = None,
    ) -> int:
        """Store one frame's images and queue its table row: ``fields`` are the table's
        columns before the offsets, ``sealed_row`` goes to a sealed session's last column.
        ``store``: stores the images itself (sealing them), instead of ``left`` and ``right``
        as they are; (offset, length, checksum) of each."""
        if self._write_error is not None:  # the last flush failed: not past it until one works
            raise SessionWriteError(
                f"{self._path}: writing failed ({self._write_error}); check free disk space and "
                "the disk"
            )
        try:
            self._sink.check()  # an earlier chunk that could not be written: not past it
        except OSError as exc:
            raise SessionWriteError(
                f"{self._path}: writing failed ({exc}); check free disk space and the disk"
            ) from exc
        try:
            if store is None:
                (lo, ll, lh), (ro, rl, rh) = cam.left.append(left), cam.right.append(right)
            else:
                (lo, ll, lh), (ro, rl, rh) = store()
        except SessionWriteError:
            raise
        except OSError as exc:  # growing the dataset failed: the frame's row is not recorded
            raise SessionWriteError(
                f"{self._path}: writing failed ({exc}); check free disk space and the disk"
            ) from exc
        tail = (sealed_row,) if self._seal is not None else ()
        cam.pending.append((*fields, lo, ll, ro, rl, lh, rh, *tail))
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

    def append_event(
        self,
        kind: EventKind | int,
        *,
        time_unix_ns: int,
        node_id: str,
        camera_serial: int = -1,
        count: int = 1,
        detail: str = "",
    ) -> int:
        """Append a session event (``EventKind``); ``camera_serial`` -1 for the node's own,
        ``count`` the occurrences the row stands for. ``node_id`` and ``detail`` are cut to
        their bounds (``EVENT_NODE_ID_BYTES``, ``EVENT_DETAIL_BYTES``). Returns its row.

        The caller bounds how many it appends (the recording aggregates a flood)."""
        self._check_open()
        code = EventKind(kind)
        if count < 1:
            raise ValueError(f"an event stands for at least 1 occurrence, got count={count}")
        self._events_pending.append(
            (
                int(time_unix_ns),
                int(code),
                event_text(node_id, EVENT_NODE_ID_BYTES),
                int(camera_serial),
                int(count),
                event_text(detail, EVENT_DETAIL_BYTES),
            )
        )
        self._events_rows += 1
        if len(self._events_pending) >= _MAX_PENDING_ROWS:
            self.flush()
        return self._events_rows - 1

    def flush(self, *, fsync: bool = False) -> None:
        """Make everything appended so far durable against a crash of this process.

        Order: image bytes, then the frame tables that point into them, then sets and gaps that
        point at frames, then the session events. ``fsync=True`` also asks the OS to put it on
        disk (power loss).
        """
        self._check_open()
        try:
            self._flush()
            if fsync:
                os.fsync(self._f.id.get_vfd_handle())
            self._write_error = None
        except OSError as exc:
            self._write_error = exc
            raise SessionWriteError(
                f"{self._path}: writing failed ({exc}); check free disk space and the disk"
            ) from exc

    def _flush(self) -> None:
        cams = self._cams.values()
        self._sink.drain()
        for cam in cams:
            for blob in (cam.left, cam.right):
                blob.flush_partial()
        for cam in cams:
            append_table_rows(cam.tables, cam.columns, cam.rows_in_file, cam.pending)
            cam.rows_in_file += len(cam.pending)
            cam.pending.clear()
        if self._sets_pending:
            start = self._sets_rows - len(self._sets_pending)
            end = start + len(self._sets_pending)
            times, members, spreads = zip(*self._sets_pending, strict=True)
            append_rows(self._set_members, start, end, np.asarray(members, dtype=np.int64))
            append_rows(self._set_spread, start, end, np.asarray(spreads, dtype=np.int64))
            append_rows(self._set_time, start, end, np.asarray(times, dtype=np.int64))
            self._sets_pending.clear()
        for ds in (self._set_members, self._set_spread, self._set_time):
            ds.flush()
        for tables, columns, rows, pending in (
            (self._gap_tables, GAP_COLUMNS, self._gaps_rows, self._gaps_pending),
            (self._event_tables, EVENT_COLUMNS, self._events_rows, self._events_pending),
        ):
            append_table_rows(tables, columns, rows - len(pending), pending)
            pending.clear()

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
            self._forget_key()
            self._sink.close()
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
            self._forget_key()
            self._sink.close()
            self._f.close()

    def _forget_key(self) -> None:
        """Drop the data key when the file is done: from then on this process holds nothing
        that opens what it wrote (the file keeps the key only wrapped for the recipients)."""
        if self._seal is not None:
            self._seal.forget()

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

    def _camera(self, serial: int) -> CameraWriter:
        self._check_open()
        try:
            return self._cams[serial]
        except KeyError:
            raise ValueError(
                f"camera {serial} is not in this session; cameras are {list(self._serials)}"
            ) from None
