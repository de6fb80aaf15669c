"""What the recorder's I/O thread does with each message an agent publishes
(``capture_agent/recorder/recorder.py``): decode it, check that it comes from the agent whose
node and cameras it names, keep the camera table (``CameraLive``, bounded by rig.toml) and refuse
frames stamped too far from the recorder's clock. A node is held to what it said it is: a frame
whose stamp is not after its camera's last, or over the camera's rate cap or byte budget
(``budget.py``), is refused too, so a stream's stored rows stay in stamp order and one node's
burst cannot take the write queue (or the disk check) from the others.

``CameraTable`` owns that state: the cameras, each agent's last status and the refusal counters
(``status`` shows them). Every refusal is counted there and logged, rate-limited
(``log_due``), and a refused frame of a take goes to ``on_refused`` (the take's session events and
accounting); no message is kept after it is handled: ``accept_frame`` says whether the frame
goes to the take, and the recorder hands it on."""

from __future__ import annotations

import collections
import logging
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from capture_agent.recorder.budget import StreamBudget, StreamLimits
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.safe_text import safe_text
from protocol.session import EventKind
from protocol.wire import (
    AgentStatus,
    FrameMessage,
    MalformedMessageError,
    UnknownVersionError,
    decode_published,
)
from protocol.wire.frame import ImageTooLargeError

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
    last_stamp_ns: int = 0  # of the last frame accepted: a stream's stamps only increase
    budget: StreamBudget | None = None  # its rate and byte caps (``budget.py``)
    # refused because the stamp went back or repeated, over the rate cap, over the byte budget
    refused: collections.Counter[EventKind] = field(default_factory=collections.Counter)

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
        self.last_stamp_ns = msg.capture_unix_ns
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
        self.images_over_limit = 0  # frames with an image over rig.toml's max_image_bytes
        self.frames_refused_sender = 0  # frames naming a node or camera not of their agent's key
        self.status_refused_sender = 0
        self.frames_refused_unknown_camera = 0  # serials not in rig.toml (or over the cap)
        # per camera, what a take learnt of its mode (else rig.toml's fps and largest image)
        self.limits: dict[int, StreamLimits] = {}
        # who hears of each refused frame (its reason and a line saying why): the take in
        # progress, which records it as a session event and in its accounting (``start.py``)
        self.on_refused: Callable[[FrameMessage, EventKind, str], None] | None = None

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

    def planned_byte_rate(self, serials: tuple[int, ...]) -> float:
        """What the given cameras should bring, bytes/s: each one's configured fps times its
        typical frame (the median of its recent frames, at most its largest); those not heard
        count 0. Not the measured rate, which one node's burst would inflate (and so stop
        every node's take at the disk check)."""
        total = 0.0
        for s in serials:
            cam = self.cameras.get(s)
            if cam is None or not cam.bytes_rx:
                continue
            limits = self.limits.get(s) or self.default_limits()
            typical = min(statistics.median(cam.bytes_rx), limits.largest_frame_bytes)
            total += limits.fps * typical
        return total

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
            msg = decode_published(parts, max_image_bytes=self.config.max_image_bytes)
        except ImageTooLargeError as exc:
            self.images_over_limit += 1
            warn_refused(self.images_over_limit, "refused frame #%d over the image limit: %s", exc)
            return None
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
        why = self.refusal(cam, msg, rx_ns)
        if why is not None:
            self.refuse(cam, msg, why)
            return False
        cam.heard(msg, time.monotonic())
        return True

    # -- a node's frames held to what the node is ------------------------------------------------
    def default_limits(self) -> StreamLimits:
        """A camera's limits before a take learns its mode: rig.toml's fps and largest image."""
        return StreamLimits(
            fps=self.config.fps, largest_frame_bytes=2 * self.config.max_image_bytes
        )

    def set_limits(self, serial: int, limits: StreamLimits) -> None:
        """A camera's rate and largest frame as the take learnt them (its buckets restart)."""
        self.limits[serial] = limits
        cam = self.cameras.get(serial)
        if cam is not None:
            cam.budget = StreamBudget(limits)

    def refusal(self, cam: CameraLive, msg: FrameMessage, rx_ns: int) -> EventKind | None:
        """Why a frame is refused, or None: a stamp that does not follow the stream's last
        (the file keeps each camera's rows in stamp order), or a frame over the camera's rate
        cap or byte budget (one node's burst must not take the write queue from the others)."""
        if cam.frames_rx and msg.capture_unix_ns <= cam.last_stamp_ns:
            return EventKind.STAMP_BACKWARDS
        if cam.budget is None:
            cam.budget = StreamBudget(self.limits.get(cam.serial) or self.default_limits())
        return cam.budget.admit(msg.left_bytes + msg.right_bytes, msg.capture_unix_ns, rx_ns)

    def refuse(self, cam: CameraLive, msg: FrameMessage, why: EventKind) -> None:
        """Count a refused frame, log it (rate-limited) and make it a session event."""
        cam.refused[why] += 1
        if why is EventKind.STAMP_BACKWARDS:
            back_ms = (cam.last_stamp_ns - msg.capture_unix_ns) / 1e6
            detail = f"frame {msg.frame_index} stamped {back_ms:.3f} ms before the last: refused"
        else:
            limits = cam.budget.limits if cam.budget else self.default_limits()
            detail = (
                f"frame {msg.frame_index} ({msg.left_bytes + msg.right_bytes} bytes) over the "
                f"cap of {limits.max_frames_per_s:g} frames/s and "
                f"{limits.max_bytes_per_s / 1e6:.1f} MB/s: refused"
            )
        if log_due(cam.refused[why]):
            log.warning(
                "camera %d on %s: %s #%d: %s",
                cam.serial,
                cam.node_id,
                why.name.lower(),
                cam.refused[why],
                detail,
            )
        if self.on_refused is not None:
            self.on_refused(msg, why, detail)

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
        cam.budget = StreamBudget(self.limits.get(cam.serial) or self.default_limits())
        log.info("camera %d streaming from %s", msg.camera_serial, msg.node_id)
        return cam
