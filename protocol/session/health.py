"""A session's health, as ``egosurg session info`` prints it and ``egosurg report`` shows it:
per camera its mode, frames, measured fps and sets it is missing from; drops and gaps per camera
and kind; the synchronised sets' spread; the take's session events per kind and node.

One function for both, so the terminal and the case report never disagree (``set_counts.py``
has the same rule for missing-in-sets counts). Reads the structure only: a sealed session opened
without an identity gives the same numbers (its case metadata values read ``<sealed>``).
"""

from __future__ import annotations

import numpy as np

from protocol.session.format import GapKind
from protocol.session.read import SessionReader
from protocol.set_counts import missing_in_sets


def summarise(reader: SessionReader) -> dict:
    """The session's health as plain JSON-able values (``egosurg session info --json``)."""
    info = reader.info
    sets = reader.sets()
    missing = missing_in_sets(sets.members, info.camera_serials)  # as the stop summary counts
    cams = []
    for serial in info.camera_serials:
        table = reader.frame_table(serial)
        stamps = table["capture_unix_ns"]
        fps = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9) if len(stamps) > 1 else 0.0
        ci = info.camera(serial)
        cams.append(
            {
                "serial": serial,
                "node_id": ci.node_id,
                "mode": f"{ci.resolution} {ci.width}x{ci.height} @ {ci.fps_nominal:g} fps",
                "encoding": ci.encoding,
                "frames": len(stamps),
                "fps_measured": round(float(fps), 2),
                "missing_in_sets": missing[serial],
            }
        )
    gaps: dict[str, dict[str, int]] = {}
    for g in reader.gaps():
        per = gaps.setdefault(str(g.camera_serial), {})
        name = GapKind(g.kind).name.lower()
        per[name] = per.get(name, 0) + max(g.missing_count, 1 if g.missing_count < 0 else 0)
    counted = [s for s in info.camera_serials if reader.frame_count(s)]
    first = min((int(reader.frame_table(s)["capture_unix_ns"][0]) for s in counted), default=0)
    last = max((int(reader.frame_table(s)["capture_unix_ns"][-1]) for s in counted), default=0)
    spread_ms = sets.spread_ns / 1e6
    complete = int((sets.members >= 0).all(axis=1).sum()) if len(sets.members) else 0
    return {
        "file": str(reader.path),
        "session": info.session_name,
        "metadata": info.case_metadata,
        "closed_cleanly": info.closed_cleanly,
        "format_version": info.format_version,
        "take_part": info.take_part,
        "previous_session_file": info.previous_session_file,
        "duration_s": round((last - first) / 1e9, 3) if last > first else 0.0,
        "sets": len(sets.set_unix_ns),
        "complete_sets": complete,
        "spread_ms": {
            "median": round(float(np.median(spread_ms)), 3) if len(spread_ms) else None,
            "p95": round(float(np.percentile(spread_ms, 95)), 3) if len(spread_ms) else None,
            "max": round(float(spread_ms.max()), 3) if len(spread_ms) else None,
        },
        "tolerance_ms": info.tolerance_ns / 1e6,
        "cameras": cams,
        "drops_and_gaps": gaps,
        "events": event_counts(reader),
    }


def event_counts(reader: SessionReader) -> dict[str, dict[str, int]]:
    """Per event kind, per node: how many times it happened (a row may stand for many)."""
    out: dict[str, dict[str, int]] = {}
    for e in reader.events():
        per = out.setdefault(e.kind.name.lower(), {})
        per[e.node_id] = per.get(e.node_id, 0) + e.count
    return out
