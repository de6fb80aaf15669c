"""What the recorder's I/O thread does with each message an agent publishes
(``capture_agent/recorder/recorder.py``): decode it, check that it comes from the agent whose
node and cameras it names, keep the camera table (``CameraLive``, bounded by rig.toml) and refuse
frames stamped too far from the recorder's clock.

``CameraTable`` owns that state: the cameras, each agent's last status and the refusal counters
(``status`` shows them). Every refusal is counted there and logged, rate-limited
(``log_due``); no message is kept after it is handled: ``accept_frame`` says whether the frame
goes to the take, and the recorder hands it on."""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field

from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.safe_text import safe_text
from protocol.wire import (
    AgentStatus,
    FrameMessage,
    MalformedMessageError,
    UnknownVersionError,
    decode_published,
)

log = logging.getLogger(__name__)

MAX_UNLISTED_CAMERAS = 64  # the camera table's bound when rig.toml lists no cameras
LIVE_WINDOW_S = 2.0


def log_due(n: int) -> bool:
    """Whether the ``n``-th of a repeated event is logged: the first five, then every 1000th,
    so a flood of bad input cannot flood the journal but still shows that it goes on."""
    return n <= 5 or n % 1000 == 0


def warn_refused(n: int, message: str, *args: object) -> None:
    """Log the ``n``-th refusal of one kind, rate-limited (``log_due``); ``message`` takes
    ``n`` as its first argument."""
    if log_due(n):
        log.warning(message, n, *args)


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

    def heard(self, msg: FrameMessage, now_monotonic: float) -> None:
        """A frame of this camera was accepted: its rate, PTP and liveness."""
        self.node_id = msg.node_id
        self.stamps.append(msg.capture_unix_ns)
        self.rx_monotonic.append(now_monotonic)
        self.bytes_rx.append(msg.left_bytes + msg.right_bytes)
        self.last_rx_monotonic = now_monotonic
        self.ptp_offset_ns = msg.ptp_offset_ns
        self.ptp_locked = msg.ptp_locked
        self.frames_rx += 1


class CameraTable:
    """The cameras and agents the recorder hears, and what it refused of what they publish.

    Changed only by the I/O thread; ``status`` and the systemd line read it (plain reads)."""

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.cameras: dict[int, CameraLive] = {}
        # node_id -> (its last status, when it came: monotonic s)
        self.agent_status: dict[str, tuple[AgentStatus, float]] = {}
        self.malformed = 0
        self.unknown_version = 0
        self.frames_refused_sender = 0  # frames naming a node or camera not of their agent's key
        self.status_refused_sender = 0
        self.frames_refused_unknown_camera = 0  # serials not in rig.toml (or over the cap)

    # -- what the rest of the recorder asks -----------------------------------------------------
    def expected(self) -> tuple[int, ...]:
        """The cameras a take records: rig.toml's, or (when it lists none) those heard."""
        return self.config.expected_cameras or tuple(sorted(self.cameras))

    def is_streaming(self, serial: int) -> bool:
        cam = self.cameras.get(serial)
        return cam is not None and cam.streaming()

    def byte_rate(self, serials: tuple[int, ...]) -> float:
        """What the given cameras stream, bytes/s (those not heard count 0)."""
        return sum(self.cameras[s].byte_rate() for s in serials if s in self.cameras)

    def listed_owner(self, serial: int) -> str | None:
        """The node rig.toml lists the camera under, if any."""
        return next((a.node_id for a in self.config.agents if serial in a.cameras), None)

    def owner(self, serial: int) -> str | None:
        """The node a camera belongs to: rig.toml's listing, else the node its frames name."""
        listed = self.listed_owner(serial)
        if listed is not None:
            return listed
        cam = self.cameras.get(serial)
        return cam.node_id if cam is not None else None

    # -- each published message -----------------------------------------------------------------
    def decode(self, parts: list, agent: AgentEndpoint) -> FrameMessage | None:
        """A message from ``agent``'s SUB socket (so, over CURVE, from that agent's key): the
        frame it carries, or None (a status is kept; anything refused is counted)."""
        try:
            msg = decode_published(parts)
        except UnknownVersionError as exc:
            self.unknown_version += 1
            warn_refused(self.unknown_version, "rejected message #%d: %s", exc)
            return None
        except MalformedMessageError as exc:
            self.malformed += 1
            warn_refused(self.malformed, "rejected malformed message #%d: %s", exc)
            return None
        if self.wrong_sender(msg, agent):
            return None
        if isinstance(msg, AgentStatus):
            self.agent_status[msg.node_id] = (msg, time.monotonic())
            return None
        return msg

    def wrong_sender(self, msg: FrameMessage | AgentStatus, agent: AgentEndpoint) -> bool:
        """True (counted, logged) for a message that names another node than the agent whose
        key sent it, or a camera that rig.toml does not list under that agent: a rogue or
        misconfigured key cannot speak for another node's cameras."""
        if isinstance(msg, AgentStatus):
            if msg.node_id == agent.node_id:
                return False
            self.status_refused_sender += 1
            n, what = self.status_refused_sender, "status"
        else:
            if msg.node_id == agent.node_id and (
                not agent.cameras or msg.camera_serial in agent.cameras
            ):
                return False
            self.frames_refused_sender += 1
            n, what = self.frames_refused_sender, f"frame of camera {msg.camera_serial}"
        warn_refused(
            n,
            f"refused {what} #%d naming node %r from the link of agent %s (cameras %s)",
            msg.node_id,
            agent.node_id,
            list(agent.cameras),
        )
        return True

    def accept_frame(self, msg: FrameMessage, rx_ns: int) -> bool:
        """Whether a decoded frame from its own agent is heard (and so goes to a take): its
        camera is in the table and its stamp near the recorder's clock."""
        cam = self.camera_for(msg)
        if cam is None:
            return False
        skew_ns = msg.capture_unix_ns - rx_ns
        if abs(skew_ns) > self.config.max_clock_skew_s * 1e9:
            # A clock step or a broken or hostile sender: such a stamp would corrupt the
            # rates and the sets (hours of empty windows), so it is refused and counted.
            cam.frames_refused_clock += 1
            warn_refused(
                cam.frames_refused_clock,
                f"camera {msg.camera_serial}: refused frame #%d stamped %.1f s %s the recorder's "
                "clock (max_clock_skew_s = %g); check PTP on %s",
                abs(skew_ns) / 1e9,
                "ahead of" if skew_ns > 0 else "behind",
                self.config.max_clock_skew_s,
                cam.node_id,
            )
            return False
        cam.heard(msg, time.monotonic())
        return True

    def camera_for(self, msg: FrameMessage) -> CameraLive | None:
        """The camera's entry; a new one only for a serial that rig.toml lists (or, when it
        lists none, while the table is under MAX_UNLISTED_CAMERAS). Others are counted."""
        owner = self.listed_owner(msg.camera_serial)
        if owner is not None and owner != msg.node_id:
            # a listed camera speaks only through its own agent (whose link checked node_id)
            self.frames_refused_sender += 1
            warn_refused(
                self.frames_refused_sender,
                "refused frame #%d of camera %d from node %s: rig.toml lists it under %s",
                msg.camera_serial,
                safe_text(msg.node_id),
                owner,
            )
            return None
        cam = self.cameras.get(msg.camera_serial)
        if cam is not None:
            return cam
        listed = self.config.expected_cameras
        if (listed and msg.camera_serial not in listed) or (
            not listed and len(self.cameras) >= MAX_UNLISTED_CAMERAS
        ):
            self.frames_refused_unknown_camera += 1
            warn_refused(
                self.frames_refused_unknown_camera,
                "refused frame #%d of camera %d from %s: %s",
                msg.camera_serial,
                msg.node_id,
                "not a camera of rig.toml"
                if listed
                else f"rig.toml lists no cameras and {MAX_UNLISTED_CAMERAS} already stream",
            )
            return None
        cam = self.cameras[msg.camera_serial] = CameraLive(msg.camera_serial, msg.node_id)
        log.info("camera %d streaming from %s", msg.camera_serial, msg.node_id)
        return cam
