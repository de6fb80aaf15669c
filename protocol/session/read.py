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

import dataclasses
import functools
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, TypeVar, cast

import h5py
import numpy as np
import xxhash

from protocol.errors import UserError
from protocol.sealing import Identity, PayloadContext, Recipient, SealedPayloadError
from protocol.session.format import (
    EVENT_COLUMNS,
    FORMAT,
    GAP_COLUMNS,
    NEWEST_FORMAT_VERSION,
    OLDEST_FORMAT_VERSION,
    SEALED_FORMAT_VERSION,
    SUMMARY_COLUMNS,
    CameraInfo,
    EventKind,
    GapKind,
    GapRecord,
    ImageChecksumError,
    ImageSealError,
    SessionEvent,
    SessionFormatError,
    SessionInfo,
    SessionNotFoundError,
    SetTable,
    frame_columns,
)
from protocol.session.layout import READ_ERRORS, check_layout
from protocol.session.open import check_superblock, read_superblock
from protocol.session.probe import open_hdf5
from protocol.session.sealed import (
    GROUP,
    IMAGE_FIELD,
    SEALED_TEXT,
    ReaderSeal,
    StoredSeal,
    read_stored_seal,
)
from protocol.session.verify import verify_session
from protocol.set_counts import missing_in_sets

logger = logging.getLogger(__name__)

READ_CACHE_BYTES = 16 << 20  # per dataset: a few chunks of the byte datasets
_F = TypeVar("_F", bound=Callable[..., Any])
SIDES = ("left", "right")


class UnknownCameraError(KeyError):
    """The caller asked for a camera the session does not have."""


class FrameRowError(IndexError):
    """The caller asked for a frame row past the end of a camera's table."""


def _guarded(what: str) -> Callable[[_F], _F]:
    """Turn any error reading the file into a ``SessionFormatError`` naming the file and part."""

    def wrap(method: _F) -> _F:
        @functools.wraps(method)
        def guarded(self: SessionReader, *args: Any, **kwargs: Any) -> Any:
            try:
                return method(self, *args, **kwargs)
            except (SessionFormatError, UnknownCameraError, FrameRowError, UserError):
                raise  # (UserError: IdentityRequiredError, a PermissionError, is not damage)
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

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        allow_truncated: bool = False,
        identity: Identity | None = None,
    ) -> None:
        """``allow_truncated``: open a file shorter than the end its superblock records, for
        ``protocol.session.recover`` (what is cut off then fails as ``SessionFormatError``).
        ``identity``: a recipient's identity, which opens a sealed session's images and case
        values (``WrongIdentityError``, naming its recipients, if it is not one of them);
        without one a sealed session's structure reads and its sealed parts raise
        ``IdentityRequiredError``. A plaintext session ignores it."""
        self._path = Path(path)
        self._f, version = _open_session(self._path, allow_truncated)
        self.columns = frame_columns(version)  # the frame table's columns in this file
        self._seal: ReaderSeal | None = None
        try:
            self._size_bytes = self._path.stat().st_size
            self.info = self._read_info(version)
            check_layout(self._path, self._f, self.info, self.columns, self._size_bytes)
            if version >= SEALED_FORMAT_VERSION:
                self._seal = self._open_seal(identity)
        except BaseException:
            self._f.close()
            raise
        self._views: dict[int, _BlobView] = {}

    @property
    def path(self) -> Path:
        return self._path

    @property
    def sealed(self) -> bool:
        """Whether the session's images and case values are sealed (format_version 3)."""
        return self._seal is not None

    @property
    def can_open(self) -> bool:
        """Whether its images can be read: a plaintext session, or a sealed one opened with
        the identity of one of its recipients."""
        return self._seal is None or self._seal.sealer is not None

    @property
    def recipients(self) -> list[Recipient]:
        """The recipients a sealed session is sealed for (none for a plaintext one): derived
        data is sealed for them. Opened with an identity, the list is the one sealed with the
        images (a list changed in the file is refused when it opens)."""
        return list(self._seal.recipients) if self._seal is not None else []

    def stored_seal(self) -> StoredSeal | None:
        """A sealed session's sealing as stored, for ``recover`` to copy; None if plaintext."""
        return self._seal.stored if self._seal is not None else None

    def require_identity(self, what: str) -> None:
        """``IdentityRequiredError`` naming ``what`` and the recipients, when the session is
        sealed and was opened without an identity."""
        if self._seal is not None and self._seal.sealer is None:
            raise self._seal.required(what)

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
                self._group(camera_serial),
                self.frame_count(camera_serial),
                self.info.has_checksums,
                sealed=self._seal is not None,
            )
        n = view.offsets.shape[0]
        if not 0 <= row < n:
            raise FrameRowError(f"camera {camera_serial} has frames 0..{n - 1}, not {row}")
        k = SIDES.index(side)
        self.require_identity(f"camera {camera_serial} row {row} {side} image")
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
        if self._seal is not None:
            ctx = PayloadContext(
                field=IMAGE_FIELD,
                camera_serial=camera_serial,
                row=int(view.sealed_rows[row]),
                side=cast(Literal["left", "right"], side),
                capture_unix_ns=int(view.captures[row]),
            )
            try:
                return self._seal.open(data, ctx)
            except SealedPayloadError:
                raise ImageSealError(self._path, camera_serial, row, side) from None
        return data

    def case_metadata(self) -> dict[str, str]:
        """The case metadata; ``IdentityRequiredError`` for a sealed session opened without an
        identity (whose ``info.case_metadata`` values read ``"<sealed>"``)."""
        self.require_identity("its case metadata")
        return dict(self.info.case_metadata)

    def rig_config_text(self) -> str:
        """The rig configuration's text, as ``case_metadata`` is guarded."""
        self.require_identity("its rig configuration text")
        return self.info.rig_config_toml

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

    def _open_seal(self, identity: Identity | None) -> ReaderSeal:
        """A sealed session's key block and recipients; with ``identity``, its data key, and
        ``info`` with the case values opened (``"<sealed>"`` without)."""
        a = self._f.attrs
        try:
            if GROUP not in self._f:
                raise KeyError(f"no /{GROUP} group")
            stored = read_stored_seal(
                self._f,
                _str_attr(a, "case_metadata_json", "{}"),
                _str_attr(a, "rig_config_toml", ""),
            )
        except READ_ERRORS as exc:
            raise SessionFormatError(
                f"{self._path}: a sealed session whose key block or recipients cannot be read "
                f"({type(exc).__name__}: {exc}); no identity can open it. Copy the file again "
                "from the recorder"
            ) from None
        seal = ReaderSeal(self._path, stored, identity)
        meta = {k: SEALED_TEXT for k in stored.case_metadata}
        rig = SEALED_TEXT
        if seal.sealer is not None:
            try:
                meta, rig = seal.open_metadata(), seal.open_rig_config()
            except (SealedPayloadError, UnicodeDecodeError) as exc:
                raise SessionFormatError(f"{self._path}: {exc}") from None
        self.info = dataclasses.replace(
            self.info, case_metadata=meta, rig_config_toml=rig, sealed=True
        )
        return seal


class _BlobView:
    """One camera's image offsets and byte datasets, cached for fast random reads."""

    def __init__(self, group: h5py.Group, rows: int, checksums: bool, *, sealed: bool) -> None:
        self.datasets = (group["left_bytes"], group["right_bytes"])
        # what a sealed image's associated data names: its sealed row and capture stamp
        self.sealed_rows = group["sealed_row"][:rows] if sealed else np.empty(0, np.uint64)
        self.captures = group["capture_unix_ns"][:rows] if sealed else np.empty(0, np.int64)
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
        if version > NEWEST_FORMAT_VERSION:
            raise SessionFormatError(
                f"{path}: session format_version {version} was written by a newer EgoSurg; "
                f"this one reads up to version {NEWEST_FORMAT_VERSION}. Upgrade egosurg."
            )
        if version < OLDEST_FORMAT_VERSION:
            raise SessionFormatError(f"{path}: invalid session format_version {version}")
    except BaseException:
        f.close()
        raise
    return f, version
