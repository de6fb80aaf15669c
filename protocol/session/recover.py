"""Copying what is intact out of a damaged session into a new, valid one.

``recover_session(damaged, target)`` opens the damaged file as far as HDF5 can (a killed
writer's file, or a truncated one: its end-of-file check is waived), then copies, into a new
session written by ``SessionWriter`` (closed cleanly, mode 0600):

- each camera's frames whose table row and both images can be read, whose images lie inside
  their byte dataset, match their checksum (format_version 2 on), and are whole JPEGs (start and
  end markers) or raw images of the right size; a table is read chunk by chunk, so the rows
  before a damaged chunk are kept;
- every synchronised set all of whose members were copied (its members renumbered to the new
  rows), whose spread matches its members' capture times and which keeps the sets' order;
- the gap records that name a session camera and a known kind;
- the root and camera attributes (name, case metadata, cameras, tolerance, rig config, take
  links). Without them there is no session to write, and that is the one refusal.

The report says what was kept and what was lost, per camera, and is stored in the new file's
``summary_json`` under ``recovered_from``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import xxhash

from protocol.session.format import GAP_COLUMNS, GapKind, SessionFormatError
from protocol.session.read import READ_ERRORS, SessionReader
from protocol.session.write import SessionWriter

logger = logging.getLogger(__name__)

_BLOCK_ROWS = 4096


@dataclass
class RecoveryReport:
    source: Path
    target: Path
    frames_kept: dict[int, int] = field(default_factory=dict)
    frames_lost: dict[int, int] = field(default_factory=dict)
    sets_kept: int = 0
    sets_lost: int = 0
    gaps_kept: int = 0
    gaps_lost: int = 0
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
            "problems": self.problems,
        }

    def lines(self) -> list[str]:
        out = [f"recovered {self.source} into {self.target}"]
        for serial, kept in self.frames_kept.items():
            out.append(f"camera {serial}: {kept} frames kept, {self.frames_lost[serial]} lost")
        out.append(f"synchronised sets: {self.sets_kept} kept, {self.sets_lost} lost")
        out.append(f"gap records: {self.gaps_kept} kept, {self.gaps_lost} lost")
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


def _intact(data: bytes | None, encoding: str, raw_bytes: int, digest: int | None) -> bool:
    if data is None:
        return False
    if digest is not None and xxhash.xxh3_64_intdigest(data) != digest:
        return False
    if encoding == "jpeg":
        return len(data) >= 4 and data[:2] == b"\xff\xd8" and data[-2:] == b"\xff\xd9"
    return len(data) == raw_bytes


def recover_session(source: Path | str, target: Path | str) -> RecoveryReport:
    """Copy what is intact in ``source`` into a new session ``target``; see the module doc."""
    source, target = Path(source), Path(target)
    report = RecoveryReport(source, target)
    try:
        reader = SessionReader(source, allow_truncated=True)
    except SessionFormatError as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        raise SessionFormatError(
            f"nothing can be recovered from {source}: {exc}. Without the file's structure and "
            "the session's attributes its frames cannot be located; keep the file as it is"
        ) from None
    existed = target.exists()  # then the writer refuses it, and it is not ours to remove
    try:
        _recover(reader, target, report)
    except BaseException:
        if not existed:  # never leave a half-written copy that looks like a recovery
            target.unlink(missing_ok=True)
        raise
    finally:
        reader.close()
    logger.debug("%s", "; ".join(report.lines()))
    return report


def _recover(reader: SessionReader, target: Path, report: RecoveryReport) -> None:
    info = reader.info
    f = reader.h5
    with SessionWriter(
        target,
        session_name=info.session_name,
        case_metadata=info.case_metadata,
        cameras=list(info.cameras),
        tolerance_ns=info.tolerance_ns,
        rig_config_text=info.rig_config_toml,
        software_version=info.software_version,
        started_unix_ns=info.started_unix_ns,
        previous_session_file=info.previous_session_file if info.take_part > 1 else "",
        take_part=info.take_part if info.previous_session_file else 1,
    ) as writer:
        row_maps: dict[int, dict[int, int]] = {}
        captures: dict[int, np.ndarray] = {}
        for cam in info.cameras:
            serial = cam.camera_serial
            row_maps[serial], captures[serial] = {}, np.empty(0, np.int64)
            try:
                row_maps[serial], captures[serial] = _copy_frames(reader, writer, cam, report)
            except READ_ERRORS as exc:
                report.frames_kept.setdefault(serial, 0)
                report.frames_lost.setdefault(serial, 0)
                report.problems.append(f"camera {serial}: cannot be read ({exc})")
        try:
            _copy_sets(f, writer, info.camera_serials, row_maps, captures, report)
        except READ_ERRORS as exc:
            report.problems.append(f"the synchronised sets cannot be read ({exc})")
        try:
            _copy_gaps(f, writer, info.camera_serials, report)
        except READ_ERRORS as exc:
            report.problems.append(f"the gap records cannot be read ({exc})")
        stopped = info.stopped_unix_ns or max(
            (int(c.max()) for c in captures.values() if c.size), default=time.time_ns()
        )
        writer.close(stopped, {"recovered_from": report.as_dict()})


def _copy_frames(
    reader: SessionReader, writer: SessionWriter, cam: Any, report: RecoveryReport
) -> tuple[dict[int, int], np.ndarray]:
    serial = cam.camera_serial
    group = reader.h5[f"cameras/{serial}"]
    problems: list[str] = []
    table = _table(group, reader.columns, problems)
    declared = max(group[name].shape[0] for name in reader.columns)
    blobs = (group["left_bytes"], group["right_bytes"])
    raw_bytes = cam.width * cam.height * 3
    row_map: dict[int, int] = {}
    kept_capture = []
    damaged = 0
    for row in range(table["capture_unix_ns"].shape[0]):
        images = []
        for side, ds in zip(("left", "right"), blobs, strict=True):
            data = _image(ds, int(table[f"{side}_offset"][row]), int(table[f"{side}_length"][row]))
            digest = int(table[f"{side}_xxh3_64"][row]) if f"{side}_xxh3_64" in table else None
            images.append(data if _intact(data, cam.encoding, raw_bytes, digest) else None)
        if images[0] is None or images[1] is None:
            damaged += 1
            continue
        row_map[row] = writer.append_frame(
            serial,
            left=images[0],
            right=images[1],
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
    report.frames_kept[serial] = len(row_map)
    report.frames_lost[serial] = declared - len(row_map)
    report.problems += problems
    return row_map, np.asarray(kept_capture, dtype=np.int64)


def _copy_sets(
    f: h5py.File,
    writer: SessionWriter,
    serials: tuple[int, ...],
    row_maps: dict[int, dict[int, int]],
    captures: dict[int, np.ndarray],
    report: RecoveryReport,
) -> None:
    problems: list[str] = []
    sets = _table(f["sets"], ("set_unix_ns", "members", "spread_ns"), problems)
    declared = max(f[f"sets/{n}"].shape[0] for n in ("set_unix_ns", "members", "spread_ns"))
    last_time = None
    last_rows = [-1] * len(serials)
    respread = 0
    for k in range(sets["set_unix_ns"].shape[0]):
        members = []
        for c, serial in enumerate(serials):
            m = int(sets["members"][k, c])
            members.append(-1 if m == -1 else row_maps[serial].get(m, -2))
        present = [(c, m) for c, m in enumerate(members) if m >= 0]
        times = [int(captures[serials[c]][m]) for c, m in present]
        t = int(sets["set_unix_ns"][k])
        if (
            -2 in members
            or not present
            or (last_time is not None and t < last_time)
            or any(m <= last_rows[c] for c, m in present)
        ):
            continue
        spread = max(times) - min(times)
        if spread != int(sets["spread_ns"][k]):  # the frames are intact: their times decide
            respread += 1
        writer.append_set(t, members, spread)
        last_time = t
        for c, m in present:
            last_rows[c] = m
        report.sets_kept += 1
    report.sets_lost = declared - report.sets_kept
    if respread:
        problems.append(
            f"{respread} kept sets had a spread_ns that disagreed with their members' capture "
            "times; it was recomputed from them"
        )
    if report.sets_lost > len(problems):
        problems.append(f"{report.sets_lost} synchronised sets with a damaged or missing member")
    report.problems += problems


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
