"""The recorder's ``status`` reply and its one-line systemd ``STATUS=`` (``recorder.py``).

The reply's fields are a contract (docs/capture.md#the-status-reply): per camera and per agent
what streams and how PTP fares, what the links and the recorder refused (counts only, so the
reply stays small whatever a sender makes up), how the I/O loop and the take's writer fare, the
last stop's summary and a take resumed after a kill."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from protocol.safe_text import safe_text

if TYPE_CHECKING:
    from capture_agent.recorder.recorder import Recorder


def link_counts(recorder: Recorder) -> dict[str, Any]:
    """What the links refused, for ``status``."""
    return {
        "auth_refused": recorder.guard.refused if recorder.guard is not None else {},
        "frames_refused_sender": recorder.frames_refused_sender,
        "status_refused_sender": recorder.status_refused_sender,
        "insecure": recorder.config.security.insecure,
    }


def status(recorder: Recorder, stall_limit_s: float) -> dict[str, Any]:
    rec = recorder.recording
    cams = []
    serials = sorted(set(recorder.cameras) | set(recorder.config.expected_cameras))
    totals = rec.accounting.totals() if rec else {}
    for s in serials:
        cam = recorder.cameras.get(s)
        agent_drops = None
        if cam is not None and cam.node_id in recorder.agent_status:
            for cs in recorder.agent_status[cam.node_id][0].cameras:
                if cs.camera_serial == s:
                    agent_drops = cs.frames_dropped
        cams.append(
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
            }
        )
    agents = []
    for a in recorder.config.agents:
        st = recorder.agent_status.get(a.node_id)
        agents.append(
            {
                "node_id": a.node_id,
                "frames": a.frames,
                "control": a.control,
                "public_key": recorder._server_keys.get(a.frames, b"").decode(),
                "alive": bool(st and time.monotonic() - st[1] < recorder.config.agent_timeout_s),
                "ptp_state": st[0].ptp.state if st else None,
                "ptp_offset_ns": st[0].ptp.master_offset_ns if st else None,
            }
        )
    out: dict[str, Any] = {
        "rig_name": recorder.config.rig_name,
        "recording": rec is not None,
        "disk_free_bytes": recorder._disk_free,
        "output_dir": recorder.config.output_dir,
        "cameras": cams,
        "agents": agents,
        "malformed_messages": recorder.malformed,
        "unknown_version_messages": recorder.unknown_version,
        "links": link_counts(recorder),
        # what the recorder refused and how its loop and control socket fare: counts, never
        # lists of what a sender made up, so the reply stays small whatever arrives
        "frames_refused_unknown_camera": recorder.frames_refused_unknown_camera,
        "frames_refused_clock": sum(c.frames_refused_clock for c in recorder.cameras.values()),
        "max_clock_skew_s": recorder.config.max_clock_skew_s,
        "control": recorder.control.counts(),
        "progress_age_s": recorder.progress.ages_s(),
        "internal_errors": recorder.internal_errors + (rec.queue.internal_errors if rec else 0),
        "stall_limit_s": stall_limit_s,
    }
    if rec is not None:
        out.update(
            {
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
        )
    if recorder.last_stop_summary is not None:
        out["last_recording"] = recorder.last_stop_summary
    if recorder._resume is not None:  # a take resumed (or to resume) after the recorder was killed
        out["take_resume"] = recorder._resume.status()
    return out


def status_line(recorder: Recorder) -> str:
    """One line for systemd's ``STATUS=`` (read from another thread: plain reads only)."""
    rec = recorder.recording
    cams = list(recorder.cameras.values())
    streaming = sum(1 for c in cams if c.streaming())
    expected = len(recorder.config.expected_cameras) or len(cams)
    if rec is not None:
        return (
            f"recording case {rec.case}: {rec.frames_written} frames written; "
            f"{streaming} of {expected} cameras streaming"
        )
    return f"idle; {streaming} of {expected} cameras streaming"
