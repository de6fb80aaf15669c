"""Copying what is intact out of a damaged session into a new, valid one.

``recover_session(damaged, target)`` opens the damaged file as far as HDF5 can (a killed
writer's file, or a truncated one: its end-of-file check is waived), then copies, into a new
session written by ``SessionWriter`` (closed cleanly, mode 0600):

- each camera's frames whose table row and both images can be read, whose images lie inside
  their byte dataset, match their checksum (format_version 2 on), and are whole JPEGs (start and
  end markers) or raw images of the right size; a table is read chunk by chunk, so the rows
  before a damaged chunk are kept. Each camera is copied on its own: a camera whose group or
  tables cannot be read is lost, the others are not;
- every synchronised set all of whose members were copied (its members renumbered to the new
  rows, a lost camera's column left out), whose spread matches its members' capture times and
  which keeps the sets' order;
- the gap records that name a session camera and a known kind, and the session events of a
  known kind (a file from before the events table has none);
- the root and camera attributes (name, case metadata, cameras, tolerance, rig config, take
  links). When the file's own reader cannot read them (a damaged string heap, a damaged camera
  group, a bad value), what is left of them is salvaged attribute by attribute and the rest is
  rebuilt from the rig text and the frames (``protocol.session.salvage``), each substitution
  listed. Only a file whose structure HDF5 cannot open, or in which no camera can be described,
  is refused.

A sealed session is copied without a key: its key block, recipients, sealed values and sealed
images as they are, each frame keeping the ``sealed_row`` its images are bound to; with an
identity each image is also opened and one that does not open is left out.

The report says what was kept and what was lost, per camera, and what was skipped or rebuilt and
why; it is stored in the new file's ``summary_json`` under ``recovered_from``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import xxhash

from protocol.sealing import OVERHEAD_BYTES, Identity, PayloadContext, SealedPayloadError
from protocol.session.format import (
    EVENT_COLUMNS,
    GAP_COLUMNS,
    SEALED_FORMAT_VERSION,
    EventKind,
    GapKind,
    SessionFormatError,
    SessionInfo,
    SessionNotFoundError,
    frame_columns,
)
from protocol.session.open import open_unprobed, read_superblock
from protocol.session.read import READ_ERRORS, SessionReader
from protocol.session.salvage import rebuild_info, salvage_attributes
from protocol.session.sealed import IMAGE_FIELD, ReaderSeal, StoredSeal, read_stored_seal
from protocol.session.write import SessionWriter

logger = logging.getLogger(__name__)

_BLOCK_ROWS = 4096


@dataclass
class RecoveryReport:
    source: Path
    target: Path
    frames_kept: dict[int, int] = field(default_factory=dict)
    frames_lost: dict[int, int] = field(default_factory=dict)  # -1: a camera wholly unreadable
    sets_kept: int = 0
    sets_lost: int = 0
    gaps_kept: int = 0
    gaps_lost: int = 0
    events_kept: int = 0
    events_lost: int = 0
    problems: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": str(self.source),
            "frames_kept": {str(k): v for k, v in self.frames_kept.items()},
            "frames_lost": {str(k): v for k, v in self.frames_lost.items()},
            "sets_kept": self.sets_kept,
            "sets_lost": self.sets_lost,
            "gaps_kept": self.gaps_kept,
            "gaps_lost": self.gaps_lost,
            "events_kept": self.events_kept,
            "events_lost": self.events_lost,
            "problems": self.problems,
        }

    def lines(self) -> list[str]:
        out = [f"recovered {self.source} into {self.target}"]
        for serial, kept in self.frames_kept.items():
            lost = self.frames_lost[serial]
            lost_text = f"{lost} lost" if lost >= 0 else "all lost (their number cannot be read)"
            out.append(f"camera {serial}: {kept} frames kept, {lost_text}")
        out.append(f"synchronised sets: {self.sets_kept} kept, {self.sets_lost} lost")
        out.append(f"gap records: {self.gaps_kept} kept, {self.gaps_lost} lost")
        out.append(f"session events: {self.events_kept} kept, {self.events_lost} lost")
        out += [f"- {p}" for p in self.problems]
        return out


def _prefix(ds: h5py.Dataset, rows: int, failures: list[tuple[str, int, str]]) -> np.ndarray:
    """The rows of ``ds`` up to the first block that cannot be read."""
    parts = []
    for start in range(0, rows, _BLOCK_ROWS):
        try:
            parts.append(np.asarray(ds[start : min(start + _BLOCK_ROWS, rows)]))
        except READ_ERRORS as exc:
            failures.append((str(ds.name).rsplit("/", 1)[-1], start, str(exc)))
            break
    if not parts:
        return np.empty((0, *ds.shape[1:]), dtype=ds.dtype)
    return np.concatenate(parts)


def _table(group: h5py.Group, names: Any, problems: list[str]) -> dict[str, np.ndarray]:
    """The columns ``names`` of a table, cut to the rows every column could give."""
    rows = min(group[name].shape[0] for name in names)
    failures: list[tuple[str, int, str]] = []
    cols = {name: _prefix(group[name], rows, failures) for name in names}
    n = min(c.shape[0] for c in cols.values())
    if failures:
        problems.append(
            f"{group.name}: rows {n} to {rows} cannot be read (columns "
            f"{', '.join(name for name, _, _ in failures)}: {failures[0][2]})"
        )
    return {name: c[:n] for name, c in cols.items()}


def _image(ds: h5py.Dataset, offset: int, length: int) -> bytes | None:
    if offset < 0 or length < 0 or offset + length > ds.shape[0]:
        return None
    try:
        return np.asarray(ds[offset : offset + length]).tobytes()
    except READ_ERRORS:
        return None


def _intact(
    data: bytes | None, encoding: str, raw_bytes: int, digest: int | None, *, sealed: bool
) -> bool:
    """An image that reads and matches its checksum, and is whole: a JPEG's markers, a raw
    image's size. A sealed image is checked by its checksum and size only (recover holds no
    key to open it; the reader checks its tag)."""
    if data is None:
        return False
    if digest is not None and xxhash.xxh3_64_intdigest(data) != digest:
        return False
    if sealed:
        return len(data) == raw_bytes + OVERHEAD_BYTES if encoding != "jpeg" else len(data) > 4
    if encoding == "jpeg":
        return len(data) >= 4 and data[:2] == b"\xff\xd8" and data[-2:] == b"\xff\xd9"
    return len(data) == raw_bytes


def recover_session(
    source: Path | str, target: Path | str, *, identity: Identity | None = None
) -> RecoveryReport:
    """Copy what is intact in ``source`` into a new session ``target``; see the module doc.
    A sealed session needs no key; with the ``identity`` of one of its recipients each image is
    also opened, and a frame whose image does not open is left out (``WrongIdentityError`` for
    an identity that is not a recipient)."""
    source, target = Path(source), Path(target)
    report = RecoveryReport(source, target)
    f, info, seal = _open(source, report)
    existed = target.exists()  # then the writer refuses it, and it is not ours to remove
    try:
        opener = ReaderSeal(source, seal, identity) if seal and identity else None
        _recover(f, info, seal, opener, target, report)
    except BaseException:
        if not existed:  # never leave a half-written copy that looks like a recovery
            target.unlink(missing_ok=True)
        raise
    finally:
        f.close()
    logger.debug("%s", "; ".join(report.lines()))
    return report


def _open(source: Path, report: RecoveryReport) -> tuple[h5py.File, SessionInfo, StoredSeal | None]:
    """The open file, its description (the reader's, or salvaged and rebuilt when the reader
    cannot describe it: see the module doc) and a sealed session's sealing as stored."""
    try:
        reader = SessionReader(source, allow_truncated=True)
        return reader.h5, reader.info, reader.stored_seal()
    except SessionNotFoundError:
        raise
    except SessionFormatError as exc:
        why = str(exc).removeprefix(f"{source}: ")
    try:
        read_superblock(source)
        f = open_unprobed(source)
    except (OSError, SessionFormatError) as exc:
        raise SessionFormatError(
            f"nothing can be recovered from {source}: {exc}. Without the file's structure its "
            "frames cannot be located; keep the file as it is"
        ) from None
    try:
        salvaged = salvage_attributes(source)
        notes = [f"the session's description cannot be read as it is ({why}); rebuilt from it"]
        info = rebuild_info(source, f, salvaged, notes)
        seal = _salvaged_seal(source, f, info)
    except BaseException as exc:
        f.close()
        if isinstance(exc, SessionFormatError):
            raise SessionFormatError(
                f"nothing can be recovered from {source}: {exc}; keep the file as it is"
            ) from None
        raise
    report.problems += [*notes[:1], *salvaged.problems, *notes[1:]]
    for group in salvaged.groups:  # a camera that cannot be described: all its frames lost
        serial = int(group.rsplit("/", 1)[-1]) if group.rsplit("/", 1)[-1].isdigit() else -1
        if serial >= 0 and serial not in info.camera_serials:
            report.frames_kept[serial] = 0
            try:
                report.frames_lost[serial] = int(f[group]["capture_unix_ns"].shape[0])
            except READ_ERRORS:
                report.frames_lost[serial] = -1  # its group cannot be read: nor its length
    return f, info, seal


def _salvaged_seal(source: Path, f: h5py.File, info: SessionInfo) -> StoredSeal | None:
    """A sealed session's sealing read from the file as it is: without its key block no
    identity opens any image, so there is nothing to recover."""
    if info.format_version < SEALED_FORMAT_VERSION:
        return None
    try:
        return read_stored_seal(f, json.dumps(info.case_metadata), info.rig_config_toml)
    except READ_ERRORS as exc:
        raise SessionFormatError(
            f"its key block or recipients cannot be read ({exc}): no identity can open its images"
        ) from None


def _recover(
    f: h5py.File,
    info: SessionInfo,
    seal: StoredSeal | None,
    opener: ReaderSeal | None,
    target: Path,
    report: RecoveryReport,
) -> None:
    """Copy into ``target``; a sealed session's key block, recipients, sealed values and
    images as they are (``seal``: no key is needed; ``opener``, given an identity, checks that
    each image opens)."""
    columns = frame_columns(info.format_version)
    with SessionWriter(
        target,
        session_name=info.session_name,
        case_metadata=info.case_metadata if seal is None else {},
        cameras=list(info.cameras),
        tolerance_ns=info.tolerance_ns,
        rig_config_text=info.rig_config_toml if seal is None else "",
        sealed_copy=seal,
        software_version=info.software_version,
        started_unix_ns=info.started_unix_ns,
        previous_session_file=info.previous_session_file if info.take_part > 1 else "",
        take_part=info.take_part if info.previous_session_file else 1,
    ) as writer:
        row_maps: dict[int, dict[int, int]] = {}
        captures: dict[int, np.ndarray] = {}
        unread = set()  # cameras whose tables cannot be read at all: left out of the sets
        for cam in info.cameras:
            serial = cam.camera_serial
            row_maps[serial], captures[serial] = {}, np.empty(0, np.int64)
            try:
                row_maps[serial], captures[serial] = _copy_frames(
                    f, columns, writer, cam, report, opener
                )
            except READ_ERRORS as exc:
                unread.add(serial)
                report.frames_kept[serial] = 0
                report.frames_lost[serial] = _declared_rows(f, serial, columns)
                report.problems.append(f"camera {serial}: cannot be read ({exc})")
            if not row_maps[serial]:
                unread.add(serial)
        try:
            set_columns = _set_columns(f, info, unread, report)
            _copy_sets(f, writer, set_columns, row_maps, captures, report)
        except READ_ERRORS as exc:
            report.problems.append(f"the synchronised sets cannot be read ({exc})")
        try:
            _copy_gaps(f, writer, info.camera_serials, report)
        except READ_ERRORS as exc:
            report.problems.append(f"the gap records cannot be read ({exc})")
        try:
            _copy_events(f, writer, report)
        except READ_ERRORS as exc:
            report.problems.append(f"the session events cannot be read ({exc})")
        stopped = info.stopped_unix_ns or max(
            (int(c.max()) for c in captures.values() if c.size), default=time.time_ns()
        )
        writer.close(stopped, {"recovered_from": report.as_dict()})


def _declared_rows(f: h5py.File, serial: int, columns: Any) -> int:
    """The rows a camera's table claims, or -1 when even that cannot be read."""
    try:
        return max(int(f[f"cameras/{serial}/{name}"].shape[0]) for name in columns)
    except READ_ERRORS:
        return -1


def _set_columns(
    f: h5py.File, info: SessionInfo, unread: set[int], report: RecoveryReport
) -> tuple[int, ...]:
    """The serial of each column of the source's sets (-1: a camera not copied), or () when the
    columns cannot be matched to cameras (the source's camera_serials is lost)."""
    try:
        source = [int(x) for x in np.asarray(f.attrs["camera_serials"]).reshape(-1)]
    except READ_ERRORS:
        source = []
    members = f["sets/members"]
    if members.ndim != 2:
        report.problems.append(
            f"the synchronised sets are left out: their members table has shape {members.shape}"
        )
        return ()
    if len(source) != members.shape[1]:
        report.problems.append(
            "the synchronised sets are left out: the file no longer says which camera each of "
            "their columns is"
        )
        return ()
    lost = [s for s in source if s not in info.camera_serials or s in unread]
    if lost:
        report.problems.append(
            f"camera(s) {', '.join(map(str, lost))} kept no frame: left out of the synchronised "
            "sets, which keep the other cameras"
        )
    return tuple(-1 if s in lost else s for s in source)


def _copy_frames(
    f: h5py.File,
    columns: Any,
    writer: SessionWriter,
    cam: Any,
    report: RecoveryReport,
    opener: ReaderSeal | None,
) -> tuple[dict[int, int], np.ndarray]:
    serial = cam.camera_serial
    group = f[f"cameras/{serial}"]
    problems: list[str] = []
    table = _table(group, columns, problems)
    declared = max(group[name].shape[0] for name in columns)
    blobs = (group["left_bytes"], group["right_bytes"])
    raw_bytes = cam.width * cam.height * 3
    row_map: dict[int, int] = {}
    kept_capture = []
    damaged = unopened = 0
    for row in range(table["capture_unix_ns"].shape[0]):
        images = []
        for side, ds in zip(("left", "right"), blobs, strict=True):
            data = _image(ds, int(table[f"{side}_offset"][row]), int(table[f"{side}_length"][row]))
            digest = int(table[f"{side}_xxh3_64"][row]) if f"{side}_xxh3_64" in table else None
            intact = _intact(data, cam.encoding, raw_bytes, digest, sealed=writer.sealed)
            images.append(data if intact else None)
        if images[0] is None or images[1] is None:
            damaged += 1
            continue
        if opener is not None and not _opens(opener, serial, table, row, images):
            unopened += 1
            continue
        # a sealed image keeps the row it was sealed at (its associated data names it)
        append = writer.append_frame if not writer.sealed else writer.append_sealed_frame
        more = {"sealed_row": int(table["sealed_row"][row])} if writer.sealed else {}
        row_map[row] = append(
            serial,
            left=images[0],
            right=images[1],
            **more,
            capture_unix_ns=int(table["capture_unix_ns"][row]),
            host_receive_unix_ns=int(table["host_receive_unix_ns"][row]),
            recorder_receive_unix_ns=int(table["recorder_receive_unix_ns"][row]),
            frame_index=int(table["frame_index"][row]),
            seq=int(table["seq"][row]),
            ptp_offset_ns=int(table["ptp_offset_ns"][row]),
            ptp_locked=bool(table["ptp_locked"][row]),
        )
        kept_capture.append(int(table["capture_unix_ns"][row]))
        if len(row_map) % 256 == 0:
            writer.flush()
    if damaged:
        problems.append(f"camera {serial}: {damaged} frames whose images are damaged")
    if unopened:
        problems.append(
            f"camera {serial}: {unopened} frames whose images do not open with the session's key "
            "(changed with their checksums, or moved from another row or session)"
        )
    report.frames_kept[serial] = len(row_map)
    report.frames_lost[serial] = declared - len(row_map)
    report.problems += problems
    return row_map, np.asarray(kept_capture, dtype=np.int64)


def _opens(
    opener: ReaderSeal, serial: int, table: dict[str, np.ndarray], row: int, images: list[Any]
) -> bool:
    """Whether both sealed images of ``row`` open where they are (their AES-GCM tags)."""
    for side, data in zip(("left", "right"), images, strict=True):
        ctx = PayloadContext(
            field=IMAGE_FIELD,
            camera_serial=serial,
            row=int(table["sealed_row"][row]),
            side="left" if side == "left" else "right",
            capture_unix_ns=int(table["capture_unix_ns"][row]),
        )
        try:
            opener.open(data, ctx)
        except SealedPayloadError:
            return False
    return True


def _copy_sets(
    f: h5py.File,
    writer: SessionWriter,
    columns: tuple[int, ...],
    row_maps: dict[int, dict[int, int]],
    captures: dict[int, np.ndarray],
    report: RecoveryReport,
) -> None:
    """``columns``: the camera of each source column, -1 for one not copied (its column is left
    out of every set); () copies no set. A member whose frame was not kept is left out of its
    set (-1, as a camera missing from a set is); a set with no member left is lost."""
    problems: list[str] = []
    names = ("set_unix_ns", "members", "spread_ns")
    declared = max(f[f"sets/{n}"].shape[0] for n in names)
    if not columns:
        report.sets_lost = declared
        return
    sets = _table(f["sets"], names, problems)
    out_serials = writer.camera_serials
    last_time = None
    last_rows = dict.fromkeys(out_serials, -1)
    respread = dropped = 0
    for k in range(sets["set_unix_ns"].shape[0]):
        members, missing, in_lost_columns = _members(sets["members"][k], columns, row_maps)
        t = int(sets["set_unix_ns"][k])
        if (
            not members
            or (last_time is not None and t < last_time)
            or any(m <= last_rows[c] for c, m in members.items())
        ):
            continue
        times = [int(captures[c][m]) for c, m in members.items()]
        spread = max(times) - min(times)
        # the frames are intact: their times decide (a member left out changes it, rightly)
        changed = missing or in_lost_columns
        respread += not changed and spread != int(sets["spread_ns"][k])
        dropped += missing
        writer.append_set(t, [members.get(c, -1) for c in out_serials], spread)
        last_time = t
        last_rows.update(members)
        report.sets_kept += 1
    report.sets_lost = declared - report.sets_kept
    if respread:
        problems.append(
            f"{respread} kept sets had a spread_ns that disagreed with their members' capture "
            "times; it was recomputed from them"
        )
    if dropped:
        problems.append(
            f"{dropped} set members whose frames were not kept are left out of their sets"
        )
    if report.sets_lost:
        problems.append(
            f"{report.sets_lost} synchronised sets lost: unreadable, with no member left, or out "
            "of order"
        )
    report.problems += problems


def _members(
    row: np.ndarray, columns: tuple[int, ...], row_maps: dict[int, dict[int, int]]
) -> tuple[dict[int, int], int, int]:
    """One set's members as {serial: new row}; how many of its members' frames were not kept,
    and how many are in the columns of cameras not copied."""
    out, missing, in_lost_columns = {}, 0, 0
    for c, serial in enumerate(columns):
        m = int(row[c])
        in_lost_columns += serial == -1 and m != -1
        if serial == -1 or m == -1:
            continue
        new = row_maps[serial].get(m)
        if new is None:
            missing += 1
        else:
            out[serial] = new
    return out, missing, in_lost_columns


def _copy_gaps(
    f: h5py.File, writer: SessionWriter, serials: tuple[int, ...], report: RecoveryReport
) -> None:
    problems: list[str] = []
    gaps = _table(f["gaps"], tuple(GAP_COLUMNS), problems)
    declared = max(f[f"gaps/{n}"].shape[0] for n in GAP_COLUMNS)
    for i in range(gaps["kind"].shape[0]):
        serial, kind = int(gaps["camera_serial"][i]), int(gaps["kind"][i])
        if serial not in serials or kind not in {int(k) for k in GapKind}:
            continue
        writer.append_gap(
            serial,
            kind=kind,
            first_missing_frame_index=int(gaps["first_missing_frame_index"][i]),
            missing_count=int(gaps["missing_count"][i]),
            start_unix_ns=int(gaps["start_unix_ns"][i]),
            end_unix_ns=int(gaps["end_unix_ns"][i]),
        )
        report.gaps_kept += 1
    report.gaps_lost = declared - report.gaps_kept
    report.problems += problems


def _copy_events(f: h5py.File, writer: SessionWriter, report: RecoveryReport) -> None:
    """The session events of a known kind, in order; a file without the table has none."""
    if "events" not in f:
        return
    problems: list[str] = []
    events = _table(f["events"], tuple(EVENT_COLUMNS), problems)
    declared = max(f[f"events/{n}"].shape[0] for n in EVENT_COLUMNS)
    known = {int(k) for k in EventKind}
    for i in range(events["kind"].shape[0]):
        if int(events["kind"][i]) not in known or int(events["count"][i]) < 1:
            continue
        writer.append_event(
            int(events["kind"][i]),
            time_unix_ns=int(events["time_unix_ns"][i]),
            node_id=bytes(events["node_id"][i]).decode("utf-8", "replace"),
            camera_serial=int(events["camera_serial"][i]),
            count=int(events["count"][i]),
            detail=bytes(events["detail"][i]).decode("utf-8", "replace"),
        )
        report.events_kept += 1
    report.events_lost = declared - report.events_kept
    report.problems += problems
