"""A recording's start (``capture_agent/recorder/recorder.py``'s ``start`` verb, on its I/O
thread): the checks of the start's arguments (``start_args``), of the cameras, PTP and the disk
(each reading the part it checks), the agents' camera infos stored in the session
(``camera_infos``, each reply checked against the contract, ``protocol/wire/agent_info.py``), and
the creation of the session file and its ``Recording``, handed to the take state. A start that
cannot go ahead raises ``StartRefused`` with the reason and what to do."""

from __future__ import annotations

import logging
import math
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from capture_agent.errors import Refused
from capture_agent.recorder.accounting import StreamAccounting
from capture_agent.recorder.budget import StreamLimits
from capture_agent.recorder.disk import DiskBudget
from capture_agent.recorder.intake import CameraTable
from capture_agent.recorder.links import AgentLinks
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.sync import SyncConfig, Synchroniser
from capture_agent.recorder.take import TakeState
from capture_agent.recorder.write_queue import open_writer
from protocol import __version__
from protocol.formats.rig_config import RigConfig
from protocol.safe_text import brief, unsafe_character
from protocol.sealing import Recipient
from protocol.session import CameraInfo, EventKind, SessionWriter
from protocol.wire import FrameMessage
from protocol.wire.agent_info import AgentReplyError, AgentStatusReply

log = logging.getLogger(__name__)

CASE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # with fullmatch: no trailing \n
MAX_META_KEYS = 64
MAX_META_KEY_CHARS = 64
MAX_META_VALUE_CHARS = 4096
OPEN_WAIT_S = 5.0  # a start whose session file is not created within this long is refused


class StartRefused(Refused):
    """A start that cannot go ahead; the message says why and what to do."""


CONTRACT_DOC = "docs/capture.md#the-status-reply"


def start_args(
    args: dict[str, Any], default_planned_min: float
) -> tuple[str, dict[str, str], float]:
    """A start's case name, metadata and planned minutes, checked: they become a file
    name and a medical record's text, and are printed on operators' terminals."""
    case = args.get("case")
    if not isinstance(case, str) or not CASE_NAME.fullmatch(case):
        raise StartRefused(
            f"case name {brief(case)} is not usable as a file name; use 1 to 64 letters, "
            "digits, - _ . starting with a letter or digit"
        )
    meta = args.get("meta", {})
    if not isinstance(meta, dict):
        raise StartRefused("case metadata must be key=value text pairs")
    if len(meta) > MAX_META_KEYS:
        raise StartRefused(
            f"case metadata has {len(meta)} keys; at most {MAX_META_KEYS} are kept per case"
        )
    for key, value in meta.items():
        if not isinstance(value, str):
            raise StartRefused(
                f"case metadata {brief(key)} is {type(value).__name__}; metadata must be "
                "key=value text pairs"
            )
        if not 1 <= len(key) <= MAX_META_KEY_CHARS or len(value) > MAX_META_VALUE_CHARS:
            raise StartRefused(
                f"case metadata {brief(key)} ({len(key)}-character key, {len(value)}-"
                f"character value) is too long: keys 1 to {MAX_META_KEY_CHARS} characters, "
                f"values at most {MAX_META_VALUE_CHARS}"
            )
        bad = unsafe_character(key) or unsafe_character(value)
        if bad is not None:
            raise StartRefused(
                f"case metadata {brief(key)} holds the control character {bad}; metadata "
                "is plain text on one line: no terminal escapes, bidi controls or line breaks"
            )
    planned = args.get("planned_duration_min", default_planned_min)
    if (
        isinstance(planned, bool)
        or not isinstance(planned, int | float)
        or not math.isfinite(planned)
        or planned <= 0
    ):
        raise StartRefused(
            f"planned_duration_min = {brief(planned)}: give the planned length of the case "
            "in minutes, a number > 0 (the disk check needs it)"
        )
    return case, meta, float(planned)


def start_take(
    args: dict[str, Any],
    *,
    config: RigConfig,
    table: CameraTable,
    disk: DiskBudget,
    links: AgentLinks,
    take: TakeState,
    recipients: Sequence[Recipient] = (),
) -> dict[str, Any]:
    """Check a start and begin its take in ``take``; the start's reply. Reads the camera table,
    the disk and the agents (over ``links``); a start that cannot go ahead is refused. The
    session is sealed for ``recipients`` (none: a plaintext session, rig.toml said so)."""
    case, meta, planned_min = start_args(args, config.planned_duration_min)
    # (first: a bad start says what is bad)
    if take.recording is not None:
        raise StartRefused(
            f"already recording case '{take.recording.case}' to "
            f"{take.recording.writer.path}; stop it first (egosurg record stop)"
        )
    try:
        expected = streaming_cameras(table)
    except StartRefused:
        # a camera whose images are over the limit never streams: say that, with the numbers
        refuse_oversize_cameras(table, links)
        raise
    if config.require_ptp_lock:
        check_ptp(table, config)
    check_disk(disk, table.planned_byte_rate(expected), planned_min)
    infos = camera_infos(table, links, expected)
    check_image_limit(infos, config.max_image_bytes)
    for ci in infos:  # each camera held to its mode from now on
        table.set_limits(ci.camera_serial, camera_limits(ci, config))
    started_ns = time.time_ns()
    path = session_path(Path(config.output_dir), case, started_ns)
    previous, part = take.link(case)  # a resumed take

    def create() -> SessionWriter:
        return SessionWriter(
            path,
            recipients=tuple(recipients),  # none: rig.toml says plaintext = true
            previous_session_file=previous,
            take_part=part,
            session_name=case,
            case_metadata={str(k): v for k, v in meta.items()},
            cameras=infos,
            tolerance_ns=int(0.5e9 / config.fps),
            rig_config_text=config.toml_text,
            software_version=__version__,
            started_unix_ns=started_ns,
        )

    try:
        writer = open_writer(create, OPEN_WAIT_S)  # a stalled disk must not hold the loop
    except TimeoutError:
        raise StartRefused(
            f"the disk holding {config.output_dir} did not create the session file "
            f"within {OPEN_WAIT_S:g} s (writing stalls); check the disk, then start again"
        ) from None
    rec = new_recording(writer, config, case=case, serials=expected, started_ns=started_ns)
    rec.planned_bytes_per_s = table.planned_byte_rate(expected)
    table.on_refused = take_refusals(take)
    log.info("recording case %s to %s (%d cameras)", case, path, len(expected))
    take.started(rec, meta=meta, planned_min=planned_min, path=path, previous=previous, part=part)
    return {
        "case": case,
        "file": str(path),
        "cameras": list(expected),
        "started_unix_ns": started_ns,
    }


def streaming_cameras(table: CameraTable) -> tuple[int, ...]:
    """The cameras a take records, each streaming now; refused otherwise, naming each
    missing one, its node and when it was last heard."""
    expected = table.expected()
    if not expected:
        raise StartRefused(
            "no camera is streaming yet; check that the agents run "
            "(systemctl status egosurg-agent) and that rig.toml points at them"
        )
    missing = [s for s in expected if not table.is_streaming(s)]
    if not missing:
        return expected
    details = []
    for s in missing:
        cam = table.cameras.get(s)
        listed = table.listed_owner(s)
        node = listed if listed is not None else (cam.node_id if cam else "?")
        ago = (
            "never seen"
            if cam is None
            else f"last frame {time.monotonic() - cam.last_rx_monotonic:.1f} s ago"
        )
        details.append(f"SN{s} on {node} ({ago})")
    raise StartRefused(
        "camera(s) not streaming: "
        + "; ".join(details)
        + ". Check the agent and its cameras (egosurg status), then start again"
    )


def check_ptp(table: CameraTable, config: RigConfig) -> None:
    """Refuse a start while an agent is silent or its PTP is not locked."""
    for a in config.agents:
        st = table.agent_status.get(a.node_id)
        if st is None or time.monotonic() - st[1] > config.agent_timeout_s:
            raise StartRefused(
                f"no status from agent {a.node_id} for {config.agent_timeout_s:g} s; is it running?"
            )
        if st[0].ptp.state != "locked":
            raise StartRefused(
                f"PTP on {a.node_id} is '{st[0].ptp.state}', not locked: frames would "
                "not share one clock. Check ptp4l/phc2sys on that node (pmc -u -b 0 "
                "'GET TIME_STATUS_NP'), or set require_ptp_lock = false in rig.toml"
            )


def check_disk(disk: DiskBudget, rate_bytes_per_s: float, planned_min: float) -> None:
    """Refuse a start whose planned length at the streams' rate would eat into the reserve."""
    take_bytes = rate_bytes_per_s * planned_min * 60.0
    free = disk.measure()
    if free < disk.reserve_bytes + take_bytes:
        raise StartRefused(
            f"not enough disk: {free / 1e9:.1f} GB free in {disk.output_dir}, but a "
            f"{planned_min:g} min recording at {rate_bytes_per_s / 1e6:.1f} MB/s needs "
            f"{take_bytes / 1e9:.1f} GB plus the "
            f"{disk.reserve_gb:g} GB reserve. Free space or plan a shorter case"
        )


def session_path(output_dir: Path, case: str, started_ns: int) -> Path:
    """A new file for the take: the case and its start time, numbered if that exists."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(started_ns / 1e9))
    path = output_dir / f"{case}_{stamp}.h5"
    n = 1
    while path.exists():
        n += 1
        path = path.with_name(f"{case}_{stamp}_{n}.h5")
    return path


def camera_limits(ci: CameraInfo, config: RigConfig) -> StreamLimits:
    """What a camera may send (``budget.py``): rig.toml's fps (or its mode's, if lower) and
    both images of its mode raw, each at most rig.toml's ``max_image_bytes`` (no JPEG of a
    mode is larger than the raw image; the bucket's second of burst absorbs one that is)."""
    image = min(ci.width * ci.height * 3, config.max_image_bytes)
    return StreamLimits(fps=min(config.fps, ci.fps_nominal), largest_frame_bytes=2 * image)


def take_refusals(take: TakeState) -> Callable[[FrameMessage, EventKind, str], None]:
    """Where the camera table's refusals go: to the take in progress, if any."""

    def record(msg: FrameMessage, why: EventKind, detail: str) -> None:
        if take.recording is not None:
            take.recording.refused_frame(msg, why, detail)

    return record


def new_recording(
    writer: SessionWriter,
    config: RigConfig,
    *,
    case: str,
    serials: tuple[int, ...],
    started_ns: int,
) -> Recording:
    """The take's recording over its open session file: synchroniser, drop accounting and
    write queue as rig.toml sets them."""
    return Recording(
        writer=writer,
        sync=Synchroniser(
            SyncConfig(
                camera_serials=serials,
                fps=config.fps,
                max_wait_ns=int(config.max_wait_ms * 1e6),
            )
        ),
        accounting=StreamAccounting(fps=config.fps),
        case=case,
        started_unix_ns=started_ns,
        started_monotonic=time.monotonic(),
        serials=serials,
        last_flush=time.monotonic(),
        write_queue_bytes=int(config.write_queue_mb * 1e6),
    )


def camera_infos(
    table: CameraTable, links: AgentLinks, serials: tuple[int, ...]
) -> list[CameraInfo]:
    """Ask each agent for its cameras' modes and factory files (stored in the session).

    The reply is checked field by field (``protocol/wire/agent_info.py``): an agent that does
    not answer, answers ``ok: false`` or breaks the contract is refused with that reason.
    """
    infos: dict[int, CameraInfo] = {}
    for a in table.config.agents:
        needed = bool(a.cameras) or any(
            s in table.cameras and table.cameras[s].node_id == a.node_id for s in serials
        )
        reply = agent_status_reply(links, a.node_id, a.control, needed)
        if reply is None:
            continue
        for s in a.cameras:
            if reply.camera(s) is None:
                raise StartRefused(
                    f"agent {a.node_id}'s status reply has no cameras_info entry for camera "
                    f"{s}, which rig.toml lists under it; check the serials in rig.toml "
                    f"(see {CONTRACT_DOC})"
                )
        for ci in reply.cameras_info:
            owner = table.owner(ci.camera_serial)
            if ci.camera_serial in serials and owner in (None, a.node_id):
                infos[ci.camera_serial] = ci.to_session(a.node_id)
    missing = [s for s in serials if s not in infos]
    if missing:
        raise StartRefused(f"no agent reports camera(s) {missing}; check the serials in rig.toml")
    return [infos[s] for s in serials]


def refuse_oversize_cameras(table: CameraTable, links: AgentLinks) -> None:
    """Refuse naming a listed camera whose images are over ``max_image_bytes``, if there is
    one (its agent reports it); nothing when the agents cannot say."""
    config = table.config
    if not config.expected_cameras:
        return
    try:
        infos = camera_infos(table, links, config.expected_cameras)
    except StartRefused:
        return
    check_image_limit(infos, config.max_image_bytes)


def check_image_limit(infos: list[CameraInfo], max_image_bytes: int) -> None:
    """Refuse a take with a camera whose images exceed rig.toml's ``max_image_bytes``: its
    frames would all be refused. Raw images are width x height x 3 bytes; a JPEG's size is
    not known in advance (its frames are checked as they arrive)."""
    for ci in infos:
        largest = ci.width * ci.height * 3
        if ci.encoding == "raw_bgr8" and largest > max_image_bytes:
            raise StartRefused(
                f"camera {ci.camera_serial} on {ci.node_id} sends raw_bgr8 images of "
                f"{ci.width}x{ci.height}x3 = {largest} bytes, over rig.toml's max_image_bytes "
                f"= {max_image_bytes}; set max_image_bytes = {largest} (or more) in rig.toml "
                "and restart the recorder, or set that node's encoding to jpeg"
            )


def agent_status_reply(
    links: AgentLinks, node_id: str, endpoint: str, needed: bool
) -> AgentStatusReply | None:
    """An agent's checked ``status`` reply; None for an agent whose cameras the take does
    not need and that cannot give one (logged); a refusal naming the problem otherwise."""
    try:
        reply = links.request(endpoint, "status")
        if reply is None:
            problem = (
                f"agent {node_id} does not answer on {endpoint}; is it running "
                "(systemctl status egosurg-agent on that node)?"
                + (
                    ""
                    if links.security.insecure
                    else " If it runs, check that its public_key in rig.toml is current and "
                    "that its allowed_keys list the recorder's key"
                )
            )
        elif not reply.ok:
            problem = f"agent {node_id} refused 'status': {(reply.error or '')[:300]}"
        else:
            return AgentStatusReply.from_json(reply.result, node_id=node_id)
    except AgentReplyError as exc:
        problem = f"agent {node_id}'s status reply {exc}; see {CONTRACT_DOC}"
    if needed:
        raise StartRefused(problem)
    log.warning("%s (none of its cameras is recorded)", problem)
    return None
