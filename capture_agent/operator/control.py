"""``egosurg record`` and ``egosurg status``: start, stop and watch a recording.

Examples::

    egosurg record start --case case-0042 --meta surgeon="A. Smith" --meta procedure=lobectomy
    egosurg status
    egosurg record stop

The recorder's address comes from ``--recorder``, else ``--config rig.toml``, else the
``EGOSURG_RECORDER`` environment variable, else ``tcp://127.0.0.1:5560``.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from capture_agent.operator.rig_client import RigClient
from protocol.command import CommandArgumentError, add_subcommand, command_parser
from protocol.safe_text import safe_text as _t  # every string from the recorder, terminal-safe


def _address_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--recorder", help="recorder control address, e.g. tcp://10.10.0.5:5560")
    p.add_argument("--config", help="rig.toml, to take the recorder's address from it")
    p.add_argument("--json", action="store_true", help="print the raw reply as JSON")


def _meta(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise CommandArgumentError(f"--meta {item!r} must look like key=value")
        out[key.strip()] = value
    return out


def format_summary(s: dict[str, Any]) -> str:
    lines = [
        f"case {_t(s['case'])}: {s['duration_s']:.1f} s, {s['sets']} synchronised sets, "
        f"{s['frames']} frames, {s['bytes'] / 1e6:.1f} MB",
        f"file: {_t(s['file'])}",
        f"stopped: {_t(s['reason'])}",
        "camera       frames  dropped  lost-in-transport  time-gaps  reconnects  missing-in-sets"
        "  not-written-at-stop",
    ]
    for serial, c in s["cameras"].items():
        lines.append(
            f"SN{_t(serial):<10} {c['frames']:>6} {c['dropped']:>8} {c['transport_lost']:>18} "
            f"{c['time_gaps']:>10} {c['reconnects']:>11} {c['missing_in_sets']:>16} "
            f"{c.get('not_written_at_stop', 0):>20}"
        )
    unwritten = int(s.get("frames_not_written_at_stop", 0))
    if unwritten:
        lines.append(
            f"{unwritten} frames were still queued when the recording had to stop "
            f"({_t(s['reason'])}) and are not in the file"
        )
    refused = int(s.get("frames_not_written_write_failed", 0))
    if refused or s.get("write_error"):
        per_camera = ", ".join(
            f"SN{_t(serial)} {c['not_written_write_failed']}"
            for serial, c in s["cameras"].items()
            if c.get("not_written_write_failed")
        )
        lines.append(
            f"writing the session file failed "
            f"({_t(s.get('write_error', 'see the recorder log'))}): "
            f"{refused} frames are not in the file" + (f" ({per_camera})" if per_camera else "")
        )
    stalled = int(s.get("frames_not_written_disk_stalled", 0))
    if stalled:
        lines.append(
            f"the disk stalled: {stalled} frames arrived while the write queue was full and are "
            "not in the file ("
            + ", ".join(
                f"SN{_t(serial)} {c['not_written_disk_stalled']}"
                for serial, c in s["cameras"].items()
                if c.get("not_written_disk_stalled")
            )
            + ")"
        )
    lines += _held_to_its_word(s)
    if s.get("closing"):
        lines.append(f"NOTE: {_t(s['closing'])}")
    if s.get("malformed_messages") or s.get("unknown_version_messages"):
        lines.append(
            f"rejected messages: {s['malformed_messages']} malformed, "
            f"{s['unknown_version_messages']} of an unknown version"
        )
    return "\n".join(lines)


def _held_to_its_word(s: dict[str, Any]) -> list[str]:
    """A stop summary's frames refused for breaking their camera's rate, byte budget or stamp
    order, and the take's session events (``egosurg session info`` lists them too)."""
    out = []
    refused = {serial: int(c.get("refused", 0)) for serial, c in s["cameras"].items()}
    if any(refused.values()):
        out.append(
            "refused (over the camera's rate or byte budget, or stamped out of order): "
            + ", ".join(f"SN{_t(serial)} {n}" for serial, n in refused.items() if n)
        )
    events = s.get("events") or {}
    if events:
        out.append(
            "session events: " + ", ".join(f"{_t(k)} {int(n)}" for k, n in sorted(events.items()))
        )
    return out


def format_started(result: dict[str, Any]) -> str:
    """The answer to a start, in the words of 'egosurg record start' and the console's rig."""
    return (
        f"recording case {result['case']} from {len(result['cameras'])} cameras to {result['file']}"
    )


def format_status(st: dict[str, Any]) -> str:
    head = f"rig {_t(st['rig_name'])}: "
    if st["recording"]:
        head += (
            f"RECORDING case {_t(st['case'])} for {st['duration_s']:.0f} s, {st['sets']} sets, "
            f"{st['bytes'] / 1e6:.0f} MB -> {_t(st['file'])}"
        )
    else:
        head += "idle"
    lines = [head, f"disk: {st['disk_free_bytes'] / 1e9:.1f} GB free in {_t(st['output_dir'])}"]
    lines += _sessions_at_rest(st)
    if st.get("write_error"):
        lines.append(
            f"WRITING FAILS for {st['write_failing_s']:.0f} s: {_t(st['write_error'])}; "
            f"{st['frames_not_written_write_failed']} frames not in the file so far"
        )
    lines += _write_stall(st)
    lines.append("camera       node      state      fps   dropped  ptp_offset_ns  ptp")
    for c in st["cameras"]:
        dropped = c["dropped_in_recording"] if st["recording"] else c["dropped_at_agent"]
        lines.append(
            f"SN{_t(c['serial']):<10} {_t(c['node_id'] or '-'):<9} "
            f"{'streaming' if c['streaming'] else 'NO FRAMES':<10} {c['fps']:>5.1f} "
            f"{dropped if dropped is not None else '-':>9} "
            f"{c['ptp_offset_ns'] if c['ptp_offset_ns'] is not None else '-':>14}  "
            f"{'locked' if c['ptp_locked'] else 'UNLOCKED'}"
        )
    for a in st["agents"]:
        if not a["alive"]:
            lines.append(
                f"agent {_t(a['node_id'])} ({_t(a['control'])}): NO STATUS - is it running?"
            )
        lines += _link_line(a)
    if st["malformed_messages"] or st["unknown_version_messages"]:
        lines.append(
            f"rejected messages: {st['malformed_messages']} malformed, "
            f"{st['unknown_version_messages']} of an unknown version"
        )
    if st.get("images_over_limit"):
        lines.append(
            f"refused {st['images_over_limit']} frames with an image over max_image_bytes = "
            f"{st.get('max_image_bytes', '?')}"
        )
    lines += _refusals(st)
    return "\n".join(lines)


def _link_line(agent: dict[str, Any]) -> list[str]:
    """The agent's frame link, when it is not up or has dropped, been refused or made again."""
    link = agent.get("link") or {}
    counts = [int(link.get(k, 0)) for k in ("drops", "handshake_failures", "reconnects")]
    if not link or (link.get("state") == "up" and not any(counts)):
        return []
    state = "up" if link.get("state") == "up" else f"{str(link.get('state', '?')).upper()}"
    line = (
        f"agent {_t(agent['node_id'])} frame link {state}: {counts[0]} drops, {counts[1]} "
        f"refused handshakes, {counts[2]} reconnects"
    )
    if link.get("last_cause"):
        line += f"; last: {_t(link['last_cause'])}"
    return [line]


def _sessions_at_rest(st: dict[str, Any]) -> list[str]:
    """How sessions are stored: sealed for which recipients, or in clear (said loudly)."""
    at_rest = st.get("sessions")
    if not at_rest:  # a recorder older than sealed sessions
        return []
    if not at_rest.get("sealed"):
        return ["sessions: PLAINTEXT (rig.toml [sealing] plaintext = true): not encrypted at rest"]
    return ["sessions: sealed for " + ", ".join(_t(r) for r in at_rest.get("recipients", []))]


def _refusals(st: dict[str, Any]) -> list[str]:
    """What the recorder refused, and a loop that stopped making progress."""
    out = []
    control = st.get("control") or {}
    unreadable = int(control.get("rejected_malformed", 0)) + int(
        control.get("rejected_unknown_version", 0)
    )
    unknown = int(st.get("frames_refused_unknown_camera", 0))
    clock = int(st.get("frames_refused_clock", 0))
    if unknown or clock or unreadable:
        out.append(
            f"refused: {unknown} frames of cameras not in rig.toml, {clock} frames stamped more "
            f"than {st.get('max_clock_skew_s', '?')} s off the recorder's clock, {unreadable} "
            "unreadable control requests"
        )
    held = {
        "over their camera's rate": int(st.get("frames_refused_rate", 0)),
        "over their camera's byte budget": int(st.get("frames_refused_bytes", 0)),
        "stamped before their camera's previous frame": int(st.get("frames_refused_stamp", 0)),
        "naming a node or camera not of their agent": int(
            (st.get("links") or {}).get("frames_refused_sender", 0)
        ),
    }
    if any(held.values()):
        out.append("refused frames: " + ", ".join(f"{n} {why}" for why, n in held.items() if n))
    for loop, age in (st.get("progress_age_s") or {}).items():
        if float(age) > 2.0:
            out.append(f"recorder loop {_t(loop)}: no progress for {float(age):.1f} s")
    return out


def main_record(argv: list[str]) -> int:
    parser = command_parser("egosurg record", __doc__)
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_subcommand(sub, "start", "start recording a case")
    p.add_argument("--case", required=True, help="case name (letters, digits, - _ .)")
    p.add_argument("--meta", action="append", default=[], help="case metadata key=value")
    p.add_argument("--planned-min", type=float, help="planned duration in minutes (disk check)")
    _address_args(p)
    p = add_subcommand(sub, "stop", "stop the recording and print its summary")
    _address_args(p)
    args = parser.parse_args(argv)
    rig = RigClient.connect(args.recorder, args.config)
    if args.action == "start":
        result = rig.start(args.case, args.planned_min, **_meta(args.meta))
        print(json.dumps(result, indent=2) if args.json else format_started(result))
    else:
        summary = rig.stop()
        print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def main_status(argv: list[str]) -> int:
    parser = command_parser("egosurg status", __doc__)
    _address_args(parser)
    args = parser.parse_args(argv)
    st = RigClient.connect(args.recorder, args.config).status()
    print(json.dumps(st, indent=2) if args.json else format_status(st))
    return 0


def _write_stall(st: dict[str, Any]) -> list[str]:
    """The status line of a session file whose disk stalls (or fell behind): the recorder
    queues frames while it can, then refuses and counts them."""
    stalled_s = float(st.get("write_stalled_s") or 0.0)
    refused = int(st.get("frames_not_written_disk_stalled") or 0)
    if not stalled_s and not refused:
        return []
    queued = int(st.get("write_queue_bytes") or 0) / 1e6
    limit = int(st.get("write_queue_limit_bytes") or 0) / 1e6
    if not stalled_s:
        return [f"the disk stalled earlier in this take: {refused} frames are not in the file"]
    return [
        f"WRITING STALLED for {stalled_s:.0f} s: {queued:.0f} of {limit:.0f} MB of frames wait "
        f"for the disk; {refused} frames not written so far (queue full); check the disk "
        f"holding {_t(st['output_dir'])}"
    ]
