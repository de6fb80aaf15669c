"""What the recorder's I/O thread does with each message an agent publishes
(``capture_agent/recorder/recorder.py``): decode it, check that it comes from the agent whose
node and cameras it names, keep the camera table (``CameraLive``, bounded by rig.toml) and refuse
frames
stamped too far from the recorder's clock. Every refusal is counted on the recorder and logged,
rate-limited; no message is kept after it is handled."""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from capture_agent.config import AgentEndpoint
from protocol.safe_text import safe_text
from protocol.wire import (
    AgentStatus,
    FrameMessage,
    MalformedMessageError,
    UnknownVersionError,
    decode_published,
)

if TYPE_CHECKING:
    from capture_agent.recorder.recorder import Recorder

log = logging.getLogger(__name__)

MAX_UNLISTED_CAMERAS = 64  # the camera table's bound when rig.toml lists no cameras
LIVE_WINDOW_S = 2.0


@dataclass
class CameraLive:
    """What the recorder knows about a camera from its stream, recording or not."""

    serial: int
    node_id: str
    stamps: collections.deque = field(default_factory=lambda: collections.deque(maxlen=90))
    rx_monotonic: collections.deque = field(default_factory=lambda: collections.deque(maxlen=90))
    bytes_rx: collections.deque = field(default_factory=lambda: collections.deque(maxlen=90))
    last_rx_monotonic: float = 0.0
    ptp_offset_ns: int = 0
    ptp_locked: bool = False
    frames_rx: int = 0
    frames_refused_clock: int = 0  # stamped further than max_clock_skew_s from our clock

    def fps(self) -> float:
        s = list(self.stamps)
        if len(s) < 2 or time.monotonic() - self.last_rx_monotonic > LIVE_WINDOW_S:
            return 0.0
        return (len(s) - 1) / max((s[-1] - s[0]) / 1e9, 1e-9)

    def byte_rate(self) -> float:
        t = list(self.rx_monotonic)
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        return sum(list(self.bytes_rx)[1:]) / (t[-1] - t[0])

    def streaming(self) -> bool:
        return self.frames_rx > 0 and time.monotonic() - self.last_rx_monotonic < LIVE_WINDOW_S


def on_published(recorder: Recorder, parts: list, agent: AgentEndpoint) -> None:
    """A message from ``agent``'s SUB socket (so, over CURVE, from that agent's key)."""
    rx_ns = time.time_ns()
    try:
        msg = decode_published(parts)
    except UnknownVersionError as exc:
        recorder.unknown_version += 1
        if recorder.unknown_version <= 5 or recorder.unknown_version % 1000 == 0:
            log.warning("rejected message #%d: %s", recorder.unknown_version, exc)
        return
    except MalformedMessageError as exc:
        recorder.malformed += 1
        if recorder.malformed <= 5 or recorder.malformed % 1000 == 0:
            log.warning("rejected malformed message #%d: %s", recorder.malformed, exc)
        return
    if wrong_sender(recorder, msg, agent):
        return
    if isinstance(msg, AgentStatus):
        recorder.agent_status[msg.node_id] = (msg, time.monotonic())
        return
    recorder._on_frame(msg, rx_ns)  # a method: tests plant a bug in it


def wrong_sender(recorder: Recorder, msg: FrameMessage | AgentStatus, agent: AgentEndpoint) -> bool:
    """True (counted, logged) for a message that names another node than the agent whose
    key sent it, or a camera that rig.toml does not list under that agent: a rogue or
    misconfigured key cannot speak for another node's cameras."""
    if isinstance(msg, AgentStatus):
        if msg.node_id == agent.node_id:
            return False
        recorder.status_refused_sender += 1
        n, what = recorder.status_refused_sender, "status"
    else:
        if msg.node_id == agent.node_id and (
            not agent.cameras or msg.camera_serial in agent.cameras
        ):
            return False
        recorder.frames_refused_sender += 1
        n, what = recorder.frames_refused_sender, f"frame of camera {msg.camera_serial}"
    if n <= 5 or n % 1000 == 0:
        log.warning(
            "refused %s #%d naming node %r from the link of agent %s (cameras %s)",
            what,
            n,
            msg.node_id,
            agent.node_id,
            list(agent.cameras),
        )
    return True


def on_frame(recorder: Recorder, msg: FrameMessage, rx_ns: int) -> None:
    cam = camera_for(recorder, msg)
    if cam is None:
        return
    skew_ns = msg.capture_unix_ns - rx_ns
    if abs(skew_ns) > recorder.config.max_clock_skew_s * 1e9:
        # A clock step or a broken or hostile sender: such a stamp would corrupt the
        # rates and the sets (hours of empty windows), so it is refused and counted.
        cam.frames_refused_clock += 1
        n = cam.frames_refused_clock
        if n <= 5 or n % 1000 == 0:
            log.warning(
                "camera %d: refused frame #%d stamped %.1f s %s the recorder's clock "
                "(max_clock_skew_s = %g); check PTP on %s",
                msg.camera_serial,
                n,
                abs(skew_ns) / 1e9,
                "ahead of" if skew_ns > 0 else "behind",
                recorder.config.max_clock_skew_s,
                cam.node_id,
            )
        return
    now = time.monotonic()
    cam.node_id = msg.node_id
    cam.stamps.append(msg.capture_unix_ns)
    cam.rx_monotonic.append(now)
    cam.bytes_rx.append(msg.left_bytes + msg.right_bytes)
    cam.last_rx_monotonic = now
    cam.ptp_offset_ns = msg.ptp_offset_ns
    cam.ptp_locked = msg.ptp_locked
    cam.frames_rx += 1
    # No message is kept: each pins its images (up to 128 MiB); the console's preview
    # subscribes to the agent itself (rig_client.last_frame).
    if recorder.recording is not None:
        recorder.recording.write_frame(msg, rx_ns)


def camera_for(recorder: Recorder, msg: FrameMessage) -> CameraLive | None:
    """The camera's entry; a new one only for a serial that rig.toml lists (or, when it
    lists none, while the table is under MAX_UNLISTED_CAMERAS). Others are counted."""
    owner = next(
        (a.node_id for a in recorder.config.agents if msg.camera_serial in a.cameras), None
    )
    if owner is not None and owner != msg.node_id:
        # a listed camera speaks only through its own agent (whose link checked node_id)
        recorder.frames_refused_sender += 1
        n = recorder.frames_refused_sender
        if n <= 5 or n % 1000 == 0:
            log.warning(
                "refused frame #%d of camera %d from node %s: rig.toml lists it under %s",
                n,
                msg.camera_serial,
                safe_text(msg.node_id),
                owner,
            )
        return None
    cam = recorder.cameras.get(msg.camera_serial)
    if cam is not None:
        return cam
    listed = recorder.config.expected_cameras
    if (listed and msg.camera_serial not in listed) or (
        not listed and len(recorder.cameras) >= MAX_UNLISTED_CAMERAS
    ):
        recorder.frames_refused_unknown_camera += 1
        n = recorder.frames_refused_unknown_camera
        if n <= 5 or n % 1000 == 0:
            log.warning(
                "refused frame #%d of camera %d from %s: %s",
                n,
                msg.camera_serial,
                msg.node_id,
                "not a camera of rig.toml"
                if listed
                else f"rig.toml lists no cameras and {MAX_UNLISTED_CAMERAS} already stream",
            )
        return None
    cam = recorder.cameras[msg.camera_serial] = CameraLive(msg.camera_serial, msg.node_id)
    log.info("camera %d streaming from %s", msg.camera_serial, msg.node_id)
    return cam
