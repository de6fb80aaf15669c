"""The agent status message (magic ``b"EGSH"``): an agent's heartbeat with its PTP state and
every camera's health, a JSON body after the binary prefix; and ``decode_published``, which
tells it from a frame message on the agent's PUB socket. Spec: ``protocol/wire/__init__.py``."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from protocol.safe_text import brief as _brief
from protocol.wire.checks import (
    FRAME_MAGIC,
    I64_MAX,
    I64_MIN,
    PREFIX,
    STATUS_MAGIC,
    U63,
    MalformedMessageError,
    WirePart,
    as_buffer,
    check_choice,
    check_int,
    check_node_id,
    check_nullable,
    check_prefix,
    dump_json,
    fields_json,
    json_field,
    load_json_object,
    require_object,
)
from protocol.wire.frame import MAX_FRAME_BYTES, FrameMessage

STATUS_WIRE_VERSION = 1
PTP_STATES = ("locked", "unlocked", "no_ptp4l", "no_pmc", "disabled")
CAMERA_STATES = ("streaming", "stalled", "reopening", "closed", "error")


@dataclass(frozen=True, kw_only=True)
class PtpState:
    """The agent's PTP state as read from linuxptp's ``pmc``."""

    state: str
    master_offset_ns: int | None = None
    gm_present: bool | None = None

    def __post_init__(self) -> None:
        check_choice(self.state, "ptp state", PTP_STATES)
        if self.master_offset_ns is not None:
            offset = check_int(self.master_offset_ns, "ptp master_offset_ns", I64_MIN, I64_MAX)
            object.__setattr__(self, "master_offset_ns", offset)
        check_nullable(self.gm_present, bool, "ptp gm_present", "true, false or null")

    def to_json(self) -> dict[str, Any]:
        return fields_json(self)

    @classmethod
    def from_json(cls, obj: object) -> PtpState:
        d = require_object(obj, "agent status ptp")
        return cls(
            state=json_field(d, "state", str, "agent status ptp"),
            master_offset_ns=json_field(
                d, "master_offset_ns", int, "agent status ptp", nullable=True
            ),
            gm_present=json_field(d, "gm_present", bool, "agent status ptp", nullable=True),
        )


@dataclass(frozen=True, kw_only=True)
class CameraStatus:
    """One camera's health as the agent sees it; counters run from agent start."""

    camera_serial: int
    state: str
    fps_measured: float
    frames_captured: int
    frames_dropped: int
    frames_published: int
    queue_depth: int
    reopen_count: int
    last_capture_unix_ns: int | None = None
    error: str | None = None

    _COUNTERS: ClassVar[tuple[str, ...]] = (
        "camera_serial",
        "frames_captured",
        "frames_dropped",
        "frames_published",
        "queue_depth",
        "reopen_count",
    )

    def __post_init__(self) -> None:
        where = f"camera {self.camera_serial} status"
        check_choice(self.state, f"{where} state", CAMERA_STATES)
        for name in self._COUNTERS:
            value = check_int(getattr(self, name), f"{where} {name}", 0, U63 - 1)
            object.__setattr__(self, name, value)
        fps = self.fps_measured
        is_number = isinstance(fps, int | float | np.integer | np.floating)
        if isinstance(fps, bool) or not is_number or not math.isfinite(fps):
            raise MalformedMessageError(
                f"{where} fps_measured={_brief(fps)} must be a finite number"
            )
        if fps < 0:
            raise MalformedMessageError(f"{where} fps_measured={_brief(fps)} must be >= 0")
        object.__setattr__(self, "fps_measured", float(fps))
        if self.last_capture_unix_ns is not None:
            last = check_int(self.last_capture_unix_ns, f"{where} last_capture_unix_ns", 0, I64_MAX)
            object.__setattr__(self, "last_capture_unix_ns", last)
        check_nullable(self.error, str, f"{where} error", "a string or null")

    def to_json(self) -> dict[str, Any]:
        return fields_json(self)

    @classmethod
    def from_json(cls, obj: object, where: str = "agent status camera") -> CameraStatus:
        d = require_object(obj, where)
        kwargs: dict[str, Any] = {name: json_field(d, name, int, where) for name in cls._COUNTERS}
        return cls(
            **kwargs,
            state=json_field(d, "state", str, where),
            fps_measured=json_field(d, "fps_measured", float, where),
            last_capture_unix_ns=json_field(d, "last_capture_unix_ns", int, where, nullable=True),
            error=json_field(d, "error", str, where, nullable=True),
        )


@dataclass(frozen=True, kw_only=True)
class AgentStatus:
    """An agent's heartbeat, published about once a second on the frames' PUB socket."""

    node_id: str
    sent_unix_ns: int
    status_seq: int
    ptp: PtpState
    cameras: tuple[CameraStatus, ...]
    software_version: str

    def __post_init__(self) -> None:
        check_node_id(self.node_id, "agent status")
        sent = check_int(self.sent_unix_ns, "agent status sent_unix_ns", I64_MIN, I64_MAX)
        object.__setattr__(self, "sent_unix_ns", sent)
        status_seq = check_int(self.status_seq, "agent status status_seq", 0, U63 - 1)
        object.__setattr__(self, "status_seq", status_seq)
        if not isinstance(self.ptp, PtpState):
            raise MalformedMessageError(
                f"agent status ptp must be a PtpState, got {_brief(self.ptp)}"
            )
        if isinstance(self.cameras, str | bytes) or not isinstance(self.cameras, Sequence):
            raise MalformedMessageError(
                "agent status cameras must be a sequence of CameraStatus, got "
                f"{_brief(self.cameras)}"
            )
        cameras = tuple(self.cameras)
        for cam in cameras:
            if not isinstance(cam, CameraStatus):
                raise MalformedMessageError(
                    f"agent status cameras must hold CameraStatus records, got {_brief(cam)}"
                )
        object.__setattr__(self, "cameras", cameras)
        if not isinstance(self.software_version, str):
            raise MalformedMessageError(
                f"agent status software_version={_brief(self.software_version)} must be a string"
            )

    def to_json(self) -> dict[str, Any]:
        return {
            "node_id": self.node_id,
            "sent_unix_ns": self.sent_unix_ns,
            "status_seq": self.status_seq,
            "software_version": self.software_version,
            "ptp": self.ptp.to_json(),
            "cameras": [cam.to_json() for cam in self.cameras],
        }

    def to_parts(self) -> list[bytes]:
        """``[b"EGSH" + version + JSON]``, one part for ``send_multipart``."""
        body = dump_json(self.to_json(), "agent status")
        return [PREFIX.pack(STATUS_MAGIC, STATUS_WIRE_VERSION) + body]

    @classmethod
    def from_parts(cls, parts: Sequence[WirePart]) -> AgentStatus:
        if len(parts) == 0:
            raise MalformedMessageError("agent status message has 0 parts, expected 1")
        buf = as_buffer(parts[0], "agent status")
        check_prefix(buf, STATUS_MAGIC, STATUS_WIRE_VERSION, "agent status")
        if len(parts) != 1:
            raise MalformedMessageError(f"agent status message has {len(parts)} parts, expected 1")
        d = load_json_object(buf[PREFIX.size :], "agent status")
        where = "agent status"
        cams = json_field(d, "cameras", list, where)
        return cls(
            node_id=json_field(d, "node_id", str, where),
            sent_unix_ns=json_field(d, "sent_unix_ns", int, where),
            status_seq=json_field(d, "status_seq", int, where),
            software_version=json_field(d, "software_version", str, where),
            ptp=PtpState.from_json(json_field(d, "ptp", dict, where)),
            cameras=tuple(
                CameraStatus.from_json(c, f"agent status cameras[{i}]") for i, c in enumerate(cams)
            ),
        )


def decode_published(
    parts: Sequence[WirePart], *, max_image_bytes: int = MAX_FRAME_BYTES
) -> FrameMessage | AgentStatus:
    """Decode anything an agent publishes, by the magic at the start of the first part; a
    frame's images over ``max_image_bytes`` raise ``ImageTooLargeError``."""
    if len(parts) == 0:
        raise MalformedMessageError("published message has 0 parts")
    first = as_buffer(parts[0], "published message")
    if len(first) < 4:
        raise MalformedMessageError(
            f"published message first part is {len(first)} bytes, too short for a 4-byte magic"
        )
    magic = bytes(first[:4])
    if magic == FRAME_MAGIC:
        return FrameMessage.from_parts(parts, max_image_bytes=max_image_bytes)
    if magic == STATUS_MAGIC:
        return AgentStatus.from_parts(parts)
    raise MalformedMessageError(
        f"header magic {_brief(magic)} is not an EgoSurg message "
        f"(frames start with {FRAME_MAGIC!r}, agent status with {STATUS_MAGIC!r})"
    )
