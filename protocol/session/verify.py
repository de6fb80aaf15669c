"""``SessionReader.verify()``: every integrity check of a session file, one line per problem.

The checks are listed in ``docs/session.md`` ("verify()"). Content damage (an image whose bytes
no longer match their checksum, a set pointing at a missing frame, ...) is reported as
``error:`` lines; a file whose structure cannot be read at all raises ``SessionFormatError``
from the reader instead. Images are read once, in blocks of ``_CHECK_BLOCK`` bytes.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import h5py
import numpy as np
import xxhash

from protocol.sealing import OVERHEAD_BYTES
from protocol.session.format import (
    EVENT_COLUMNS,
    GAP_COLUMNS,
    EventKind,
    GapKind,
    ImageChecksumError,
    ImageSealError,
)

# The SessionReader being verified (not imported: session_read imports this module).
SessionReader = Any

_CHECK_BLOCK = 16 << 20


def verify_session(r: SessionReader, *, check_images: bool = True) -> list[str]:
    """Integrity problems, each a line starting "error:" or "note:"; empty means OK.

    A note is what a writer that was killed or is still writing leaves (unequal table
    lengths, sets ahead of their frames); on a cleanly closed file the same is an error.
    ``check_images`` reads every image once (the whole byte datasets, in 16 MiB blocks): its
    XXH3-64 against the stored one (format_version 2 on) and a JPEG's start and end markers.
    """
    clean = r.info.closed_cleanly
    # What a killed or live writer leaves behind is expected there, and damage otherwise.
    tail = "error" if clean else "note"
    problems = []
    if not clean:
        problems.append(
            "note: not closed cleanly (the writer was killed or is still writing); "
            "everything up to its last flush() is readable"
        )
    groups = set(r._f["cameras"].keys())
    expected = {str(s) for s in r.info.camera_serials}
    if groups != expected:
        problems.append(
            f"error: /cameras holds {sorted(groups)} but camera_serials is {sorted(expected)}"
        )
    if not r.info.has_checksums:
        problems.append(
            f"note: no checksums (format version {r.info.format_version}): images are checked "
            "for their JPEG markers and sizes only"
        )
    if r.sealed and not r.can_open:
        problems.append(
            f"note: sealed for {', '.join(x.label() for x in r.recipients)}; without an "
            "identity each image is checked against its checksum only (with one, every image "
            "is opened and its AES-GCM tag checked too)"
        )
    for serial in r.info.camera_serials:
        problems += _verify_camera(r, serial, tail, check_images)
    problems += _verify_sets(r, tail)
    problems += _verify_gaps(r, tail)
    problems += _verify_events(r, tail)
    if clean:
        problems += _verify_summary(r)
    return problems


def _verify_camera(r: SessionReader, serial: int, tail: str, check_images: bool) -> list[str]:
    g = r._group(serial)
    info = r.info.camera(serial)
    out = _ragged_columns(tail, f"camera {serial}: frame table", g, r.columns)
    t = r.frame_table(serial)
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
            overhead = OVERHEAD_BYTES if r.sealed else 0  # a sealed image's nonce, tag, version
            wrong = np.flatnonzero(len_in != info.width * info.height * 3 + overhead)
            if wrong.size:
                out.append(
                    f"error: camera {serial}: {side} raw_bgr8 images of rows "
                    f"{_rows(inside[wrong])} are not {info.width}x{info.height}x3 bytes"
                )
        elif check_images and not r.sealed:  # a sealed image's markers are checked opened
            wrong = np.flatnonzero(_bad_jpeg(ds, off_in, len_in))
            if wrong.size:
                out.append(
                    f"error: camera {serial}: {side} images of rows {_rows(inside[wrong])} "
                    "are not JPEG (must start with FF D8 and end with FF D9)"
                )
        if check_images and r.info.has_checksums:
            stored = t[f"{side}_xxh3_64"][inside]
            wrong = _bad_checksums(ds, off_in, len_in, stored)
            if wrong.size:
                out.append(
                    f"error: camera {serial}: {side} images of rows "
                    f"{_rows(inside[wrong], limit=1000)} do not match their checksums "
                    "(xxh3_64): their bytes changed after they were recorded"
                )
        if check_images and r.sealed and r.can_open:
            out += _verify_opened(r, serial, side, inside, jpeg=info.encoding == "jpeg")
    return out


def _verify_opened(
    r: SessionReader, serial: int, side: str, rows: np.ndarray, *, jpeg: bool
) -> list[str]:
    """A sealed session opened with an identity: every image opened (its AES-GCM tag checked,
    which also catches an image moved from another row or session with its checksum) and, once
    opened, a JPEG's markers checked."""
    unopened, not_jpeg = [], []
    for row in rows:
        try:
            image = r.image_bytes(serial, int(row), side)
        except ImageSealError:
            unopened.append(int(row))
            continue
        except ImageChecksumError:
            continue  # reported with the checksums
        if jpeg and not (
            len(image) >= 4 and image[:2] == b"\xff\xd8" and image[-2:] == b"\xff\xd9"
        ):
            not_jpeg.append(int(row))
    out = []
    if unopened:
        out.append(
            f"error: camera {serial}: {side} images of rows "
            f"{_rows(np.asarray(unopened), limit=1000)} do not open with the session's key "
            "(AES-GCM tag): changed, or moved here from another row, camera or session"
        )
    if not_jpeg:
        out.append(
            f"error: camera {serial}: {side} images of rows {_rows(np.asarray(not_jpeg))} "
            "open but are not JPEG (must start with FF D8 and end with FF D9)"
        )
    return out


def _verify_sets(r: SessionReader, tail: str) -> list[str]:
    s = r._f["sets"]
    out = _ragged_columns(tail, "sets:", s, ("set_unix_ns", "members", "spread_ns"))
    n_cams = len(r.info.camera_serials)
    if s["members"].ndim != 2 or s["members"].shape[1] != n_cams:
        return [*out, f"error: sets/members has shape {s['members'].shape}, not (N, {n_cams})"]
    table, keep = r._sets_raw()
    members = table.members
    counts = np.asarray([r.frame_count(c) for c in r.info.camera_serials])
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
    for c, serial in enumerate(r.info.camera_serials):
        cap = r.frame_table(serial)["capture_unix_ns"]
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
    for c, serial in enumerate(r.info.camera_serials):
        sets_with = np.flatnonzero(present[:, c])
        reused = np.flatnonzero(np.diff(members[sets_with, c]) <= 0) + 1
        if reused.size:
            out.append(
                f"error: camera {serial}: sets {_rows(kept[sets_with[reused]])} reuse a frame "
                "or go back in time"
            )
    return out


def _verify_gaps(r: SessionReader, tail: str) -> list[str]:
    out = _ragged_columns(tail, "gaps:", r._f["gaps"], GAP_COLUMNS)
    cols = r._gaps_raw()
    unknown = np.flatnonzero(~np.isin(cols["kind"], [int(k) for k in GapKind]))
    if unknown.size:
        out.append(f"error: gap records {_rows(unknown)} have an unknown kind")
    strangers = np.flatnonzero(~np.isin(cols["camera_serial"], r.info.camera_serials))
    if strangers.size:
        out.append(f"error: gap records {_rows(strangers)} name a camera not in the session")
    backwards = np.flatnonzero(cols["end_unix_ns"] < cols["start_unix_ns"])
    if backwards.size:
        out.append(f"error: gap records {_rows(backwards)} end before they start")
    return out


def _verify_events(r: SessionReader, tail: str) -> list[str]:
    """The session events' table checked. A file written before the table existed has none,
    which is no problem. (What the events say is ``describe_events``: they are what happened
    during the take, not damage.)"""
    cols = r.events_raw()
    if cols is None:
        return []
    out = _ragged_columns(tail, "events:", r._f["events"], EVENT_COLUMNS)
    unknown = np.flatnonzero(~np.isin(cols["kind"], [int(k) for k in EventKind]))
    if unknown.size:
        out.append(f"error: session events {_rows(unknown)} have an unknown kind")
    serial = cols["camera_serial"]
    strangers = np.flatnonzero((serial != -1) & ~np.isin(serial, r.info.camera_serials))
    if strangers.size:
        out.append(f"error: session events {_rows(strangers)} name a camera not in the session")
    uncounted = np.flatnonzero(cols["count"] < 1)
    if uncounted.size:
        out.append(f"error: session events {_rows(uncounted)} stand for fewer than 1 occurrence")
    return out


def describe_events(r: SessionReader) -> list[str]:
    """One line per kind of session event that happened: how many times, in how many records,
    from which nodes (``egosurg session verify`` prints them after the problems)."""
    cols = r.events_raw()
    if cols is None:
        return []
    out = []
    for kind in EventKind:
        rows = np.flatnonzero(cols["kind"] == int(kind))
        if not rows.size:
            continue
        nodes = sorted({bytes(n).decode("utf-8", "replace") for n in cols["node_id"][rows]})
        shown = ", ".join(repr(n) for n in nodes[:5]) + (" ..." if len(nodes) > 5 else "")
        total = int(np.maximum(cols["count"][rows], 0).sum())
        out.append(
            f"event {kind.name.lower()}: {total} time(s) in {rows.size} record(s), from "
            f"node(s) {shown}"
        )
    return out


def _ragged_columns(tail: str, table: str, group: h5py.Group, names: Iterable[str]) -> list[str]:
    """The one warning for a table whose columns differ in length (a writer stopped between
    appending to them); the reader uses the common rows."""
    lengths = [group[name].shape[0] for name in names]
    if len(set(lengths)) <= 1:
        return []
    return [
        f"{tail}: {table} columns have {min(lengths)} to {max(lengths)} rows; "
        f"using the first {min(lengths)}"
    ]


def _verify_summary(r: SessionReader) -> list[str]:
    out = []
    summary = r.summary()
    gap_serials = r._gaps_raw()["camera_serial"]
    for serial in r.info.camera_serials:
        totals = summary.get(str(serial))
        if totals is None:
            out.append(f"error: /summary has no totals for camera {serial}")
            continue
        if totals["frames"] != r.frame_count(serial):
            out.append(
                f"error: camera {serial}: /summary counts {totals['frames']} frames, the "
                f"table holds {r.frame_count(serial)}"
            )
        if totals["gap_records"] != int(np.count_nonzero(gap_serials == serial)):
            out.append(f"error: camera {serial}: /summary gap_records disagrees with /gaps")
    return out


def _bad_checksums(
    ds: h5py.Dataset, offsets: np.ndarray, lengths: np.ndarray, stored: np.ndarray
) -> np.ndarray:
    """Indices of the images whose XXH3-64 differs from ``stored``; reads in 16 MiB blocks."""
    bad = []
    order = np.argsort(offsets, kind="stable")
    ends = offsets + lengths
    i = 0
    while i < order.size:
        start = int(offsets[order[i]])
        j = i + 1  # a block holds consecutive images, at least one, within _CHECK_BLOCK
        while j < order.size and int(ends[order[j]]) - start <= _CHECK_BLOCK:
            j += 1
        stop = int(ends[order[i:j]].max())
        block = ds[start:stop] if stop > start else np.empty(0, np.uint8)
        for k in order[i:j]:
            o = int(offsets[k]) - start
            image = np.ascontiguousarray(block[o : o + int(lengths[k])])
            if xxhash.xxh3_64_intdigest(image.data) != int(stored[k]):
                bad.append(int(k))
        i = j
    return np.asarray(sorted(bad), dtype=np.int64)


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
        stop = min(start + max(_CHECK_BLOCK, align), ds.shape[0])
        j = int(np.searchsorted(sorted_pos, stop, side="left"))
        block = ds[start:stop]
        values[order[i:j]] = block[sorted_pos[i:j] - start]
        i = j
    v = values.reshape(4, -1)
    bad[ok] = ~((v[0] == 0xFF) & (v[1] == 0xD8) & (v[2] == 0xFF) & (v[3] == 0xD9))
    return bad
