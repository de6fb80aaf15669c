"""The recorder's ``status`` reply and its one-line systemd ``STATUS=`` (``recorder.py``).

The reply's fields are a contract (docs/capture.md#the-status-reply): per camera and per agent
what streams and how PTP fares, what the links and the recorder refused (counts only, so the
reply stays small whatever a sender makes up), how the I/O loop and the take's writer fare, the
last stop's summary and a take resumed after a kill. Each function reads the parts it reports;
the recorder adds what its loop owns (``loop``)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from capture_agent.recorder.disk import DiskBudget
from capture_agent.recorder.intake import CameraTable
from capture_agent.recorder.links import AgentLinks
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.take import TakeState
from protocol.formats.sealing_config import RigSealingConfig
from protocol.safe_text import safe_text
from protocol.session import EventKind


def link_counts(table: CameraTable, links: AgentLinks) -> dict[str, Any]:
    """What the links refused, for ``status``."""
    return {
        "auth_refused": links.auth_refused(),
        "frames_refused_sender": table.frames_refused_sender,
        "status_refused_sender": table.status_refused_sender,
        "insecure": table.config.security.insecure,
    }


def status(
    table: CameraTable,
    links: AgentLinks,
    disk: DiskBudget,
    take: TakeState,
    loop: dict[str, Any],
) -> dict[str, Any]:
    """The ``status`` reply; ``loop`` is what the recorder's loop reports of itself (control
    counts, progress, internal errors, the stall limit), in that order."""
    rec = take.recording
    config = table.config
    out: dict[str, Any] = {
        "rig_name": config.rig_name,
        "recording": rec is not None,
        "disk_free_bytes": disk.free_bytes,
        "output_dir": config.output_dir,
        "cameras": camera_rows(table, rec),
        "agents": agent_rows(table, links),
        "malformed_messages": table.malformed,
        "unknown_version_messages": table.unknown_version,
        "images_over_limit": table.images_over_limit,
        "max_image_bytes": config.max_image_bytes,
        "links": link_counts(table, links),
        # what the recorder refused and how its loop and control socket fare: counts, never
        # lists of what a sender made up, so the reply stays small whatever arrives
        "frames_refused_unknown_camera": table.frames_refused_unknown_camera,
        "frames_refused_clock": sum(c.frames_refused_clock for c in table.cameras.values()),
        "frames_refused_stamp": refused(table, EventKind.STAMP_BACKWARDS),
        "frames_refused_rate": refused(table, EventKind.RATE_CAPPED),
        "frames_refused_bytes": refused(table, EventKind.BYTES_CAPPED),
        "max_clock_skew_s": config.max_clock_skew_s,
        # how sessions are stored, so the operator sees a rig that writes patient video in clear
        "sessions": sessions_at_rest(config.sealing),
        **loop,
    }
    if rec is not None:
        out.update(recording_fields(rec))
    if take.last_stop_summary is not None:
        out["last_recording"] = take.last_stop_summary
    if take.resume is not None:  # a take resumed (or to resume) after the recorder was killed
        out["take_resume"] = take.resume.status()
    return out


def sessions_at_rest(sealing: RigSealingConfig) -> dict[str, Any]:
    """``{"sealed": bool, "recipients": [file names]}``: rig.toml's ``[sealing]``, as loaded."""
    return {
        "sealed": not sealing.plaintext,
        "recipients": [Path(r).name for r in sealing.recipients],
    }


def refused(table: CameraTable, why: EventKind) -> int:
    """Frames refused for ``why``, all cameras."""
    return sum(c.refused[why] for c in table.cameras.values())


def camera_rows(table: CameraTable, rec: Recording | None) -> list[dict[str, Any]]:
    """One row per camera heard or expected."""
    rows = []
    serials = sorted(set(table.cameras) | set(table.config.expected_cameras))
    totals = rec.accounting.totals() if rec else {}
    for s in serials:
        cam = table.cameras.get(s)
        agent_drops = None
        if cam is not None and cam.node_id in table.agent_status:
            for cs in table.agent_status[cam.node_id][0].cameras:
                if cs.camera_serial == s:
                    agent_drops = cs.frames_dropped
        rows.append(
            {
                "serial": s,
                "node_id": cam.node_id if cam else None,
                "streaming": bool(cam and cam.streaming()),
                "fps": round(cam.fps(), 2) if cam else 0.0,
                "ptp_offset_ns": cam.ptp_offset_ns if cam else None,
                "ptp_locked": cam.ptp_locked if cam else False,
                "dropped_in_recording": totals[s].frames_dropped_camera if s in totals else 0,
                "dropped_at_agent": agent_drops,
                "frames_refused_clock": cam.frames_refused_clock if cam else 0,
                # a node held to what it is: stamps that went back, frames over the caps
                "frames_refused_stamp": cam.refused[EventKind.STAMP_BACKWARDS] if cam else 0,
                "frames_refused_rate": cam.refused[EventKind.RATE_CAPPED] if cam else 0,
                "frames_refused_bytes": cam.refused[EventKind.BYTES_CAPPED] if cam else 0,
            }
        )
    return rows


def agent_rows(table: CameraTable, links: AgentLinks) -> list[dict[str, Any]]:
    """One row per agent of rig.toml: its links, whether it is alive and its PTP."""
    rows = []
    for a in table.config.agents:
        st = table.agent_status.get(a.node_id)
        rows.append(
            {
                "node_id": a.node_id,
                "frames": a.frames,
                "control": a.control,
                "public_key": links.public_key(a.frames),
                "alive": bool(st and time.monotonic() - st[1] < table.config.agent_timeout_s),
                "ptp_state": st[0].ptp.state if st else None,
                "ptp_offset_ns": st[0].ptp.master_offset_ns if st else None,
                # the frame link: state, drops, refused handshakes, new sockets, last cause
                "link": links.link_counts(a.node_id),
            }
        )
    return rows


def recording_fields(rec: Recording) -> dict[str, Any]:
    """What ``status`` says of the take in progress."""
    return {
        "case": rec.case,
        "file": str(rec.writer.path),
        "duration_s": round(time.monotonic() - rec.started_monotonic, 2),
        "sets": rec.sets_written,
        "frames": rec.frames_written,
        "bytes": rec.bytes_written,
        "capture_to_durable_ms": rec.latency_ms(),
        "write_failing_s": round(rec.write_failing_s(), 1),
        "write_error": safe_text(rec.write_error, 500) if rec.write_failing_since else "",
        "frames_not_written_write_failed": sum(rec.not_written_write_failed.values()),
        # the writer thread inside one call for this long (a stalling disk), what
        # waits for it, and what a full queue refused
        "write_stalled_s": round(rec.write_stalled_s(), 1),
        "write_queue_bytes": rec.queue.queued_bytes,
        "write_queue_limit_bytes": rec.queue.max_bytes,
        "frames_not_written_disk_stalled": sum(rec.not_written_disk_stalled.values()),
    }


def status_line(table: CameraTable, rec: Recording | None) -> str:
    """One line for systemd's ``STATUS=`` (read from another thread: plain reads only)."""
    cams = list(table.cameras.values())
    streaming = sum(1 for c in cams if c.streaming())
    expected = len(table.config.expected_cameras) or len(cams)
    if rec is not None:
        return (
            f"recording case {rec.case}: {rec.frames_written} frames written; "
            f"{streaming} of {expected} cameras streaming"
        )
    return f"idle; {streaming} of {expected} cameras streaming"
