"""Reading a session file: finished, being written, or left by a killed writer.

See ``protocol.session`` for the overview and ``docs/session.md`` for the layout. Readers locate
every image by offset and length, so they read files of any blob chunking (1 MiB in the files of
the first recorders, larger since).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from protocol.session_format import (
    FORMAT,
    FORMAT_VERSION,
    FRAME_COLUMNS,
    GAP_COLUMNS,
    SUMMARY_COLUMNS,
    CameraInfo,
    GapKind,
    GapRecord,
    SessionFormatError,
    SessionInfo,
    SessionNotFoundError,
    SetTable,
)

logger = logging.getLogger(__name__)

READ_CACHE_BYTES = 16 << 20  # per dataset: a few chunks of the byte datasets
_JPEG_CHECK_BLOCK = 16 << 20


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
    align = ds.chunks[0] if ds.chunks else 1  # whole chunks: none is read twice
    i = 0
    while i < sorted_pos.size:
        start = int(sorted_pos[i]) - int(sorted_pos[i]) % align
        stop = min(start + max(_JPEG_CHECK_BLOCK, align), ds.shape[0])
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
        f = h5py.File(path, "r", swmr=True, rdcc_nbytes=READ_CACHE_BYTES, rdcc_nslots=10007)
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
