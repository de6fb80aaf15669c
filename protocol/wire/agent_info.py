"""An agent's answer to the control verb ``status``, validated field by field.

The recorder asks every agent for ``status`` when a recording starts. The reply's ``result`` is
the only source of each camera's mode (``resolution``, ``width``, ``height``, ``fps``,
``encoding``) and factory calibration file in the session, so a reply that lacks a field or
carries a wrong one must be refused with the field's name, not crash the start. The contract is
written out in ``docs/capture.md`` ("Writing an agent: the contract"); in short::

    {"cameras_info": [                          required, 1..MAX_CAMERAS_PER_AGENT entries
        {"camera_serial": 41234567,             required, integer 1..2**63-1, unique in the list
         "resolution": "HD1200",                required, 1..32 of A-Z a-z 0-9 _ . - ; a ZED X
                                                mode name (HD1200, HD1080, SVGA) must match
                                                width x height
         "width": 1920, "height": 1200,         required, integers 1..8192, pixels per image
         "fps": 30,                             required, number, 0 < fps <= MAX_FPS
         "encoding": "jpeg",                    required, "jpeg" or "raw_bgr8"
         "factory_conf": "[LEFT_CAM_FHD1200]\\n..."}  required, text (<= 64 KiB) or null/""
     ],                                         when the camera has none
     "status": {...}}                           optional: an agent status message's JSON body;
                                                when present it is checked, and its node_id
                                                must be the agent's node_id in rig.toml

Fields this code does not know are ignored (JSON messages may grow without a version bump).
Every problem raises ``AgentReplyError`` (a ``MalformedMessageError``) whose ``field`` is the
path of the offending field (``cameras_info[0].resolution``) and whose message reads after
"agent node-x's status reply ...": "lacks cameras_info[0].resolution".
"""

from __future__ import annotations

import math
import re
from dataclasses import InitVar, dataclass
from typing import Any

from protocol.camera import Resolution
from protocol.session.format import CameraInfo
from protocol.wire import (
    MAX_IMAGE_SIDE_PX,
    AgentStatus,
    CameraStatus,
    Encoding,
    MalformedMessageError,
    PtpState,
)
from protocol.wire.checks import fields_json

MAX_CAMERAS_PER_AGENT = 16
MAX_FACTORY_CONF_BYTES = 64 * 1024  # a ZED SN<serial>.conf is about 3 KB
MAX_FPS = 1000.0
_U63 = 2**63
_RESOLUTION = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,31}")  # fullmatch: no trailing \n
_ZED_MODES = {r.value: r.size for r in Resolution}
_SHOW_CHARS = 60
_ENCODINGS = tuple(e.value for e in Encoding)
_CAMERA_STATUS_FIELDS = (
    "camera_serial", "state", "fps_measured", "frames_captured", "frames_dropped",
    "frames_published", "queue_depth", "reopen_count", "last_capture_unix_ns", "error",
)  # fmt: skip


class AgentReplyError(MalformedMessageError):
    """An agent's reply that breaks the contract; ``field`` names the offending field."""

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(problem)
        self.field = field


def _show(value: object) -> str:
    """``repr`` of a value from the network, bounded (repr escapes control characters)."""
    text = repr(value)
    return text if len(text) <= _SHOW_CHARS else text[: _SHOW_CHARS - 3] + "..."


def _bad(path: str, value: object, must: str) -> AgentReplyError:
    return AgentReplyError(path, f"has {path} = {_show(value)}, which must be {must}")


def _require(d: dict[str, Any], key: str, path: str) -> Any:
    full = f"{path}.{key}" if path else key
    if key not in d:
        raise AgentReplyError(full, f"lacks {full}")
    return d[key]


def _int(value: object, path: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise _bad(path, value, f"an integer from {lo} to {hi}")
    return value


@dataclass(frozen=True, kw_only=True)
class AgentCameraInfo:
    """One entry of ``cameras_info``: what the session stores about a camera at a start."""

    camera_serial: int
    resolution: str
    width: int
    height: int
    fps: float
    encoding: str
    factory_conf: str = ""
    where: InitVar[str] = "cameras_info entry"

    def __post_init__(self, where: str) -> None:
        _int(self.camera_serial, f"{where}.camera_serial", 1, _U63 - 1)
        if not isinstance(self.resolution, str) or not _RESOLUTION.fullmatch(self.resolution):
            raise _bad(
                f"{where}.resolution",
                self.resolution,
                "a mode name of 1..32 letters, digits, _ . - (HD1200, HD1080, SVGA for a ZED X)",
            )
        _int(self.width, f"{where}.width", 1, MAX_IMAGE_SIDE_PX)
        _int(self.height, f"{where}.height", 1, MAX_IMAGE_SIDE_PX)
        mode = _ZED_MODES.get(self.resolution)
        if mode is not None and mode != (self.width, self.height):
            raise AgentReplyError(
                f"{where}.resolution",
                f"says {where}.resolution = {self.resolution!r} but width x height = "
                f"{self.width}x{self.height}; {self.resolution} is {mode[0]}x{mode[1]}",
            )
        fps = self.fps
        if (
            isinstance(fps, bool)
            or not isinstance(fps, int | float)
            or not math.isfinite(fps)
            or not 0 < fps <= MAX_FPS
        ):
            raise _bad(f"{where}.fps", fps, f"a number above 0 and at most {MAX_FPS:g}")
        object.__setattr__(self, "fps", float(fps))
        if not isinstance(self.encoding, str) or self.encoding not in _ENCODINGS:
            raise _bad(
                f"{where}.encoding", self.encoding, " or ".join(f'"{e}"' for e in _ENCODINGS)
            )
        object.__setattr__(self, "encoding", str(Encoding(self.encoding).value))
        conf = "" if self.factory_conf is None else self.factory_conf
        if not isinstance(conf, str):
            raise _bad(f"{where}.factory_conf", conf, "the factory file's text, or null")
        try:
            size = len(conf.encode("utf-8"))  # JSON allows lone surrogates; a file cannot hold them
        except UnicodeEncodeError:
            size = -1
        if size < 0 or "\0" in conf:
            raise _bad(f"{where}.factory_conf", conf, "text (UTF-8, no NUL characters), or null")
        if size > MAX_FACTORY_CONF_BYTES:
            raise AgentReplyError(
                f"{where}.factory_conf",
                f"has a {where}.factory_conf of {size} bytes, above the "
                f"{MAX_FACTORY_CONF_BYTES}-byte limit",
            )
        object.__setattr__(self, "factory_conf", conf)

    @classmethod
    def from_json(cls, obj: object, where: str = "cameras_info[0]") -> AgentCameraInfo:
        if not isinstance(obj, dict):
            raise _bad(where, obj, "a JSON object")
        kwargs = {
            name: _require(obj, name, where)
            for name in ("camera_serial", "resolution", "width", "height", "fps", "encoding")
        }
        return cls(**kwargs, factory_conf=_require(obj, "factory_conf", where), where=where)

    def to_json(self) -> dict[str, Any]:
        return fields_json(self)  # ``where`` is an InitVar, not a field: it stays off the wire

    def to_session(self, node_id: str) -> CameraInfo:
        """The session's description of this camera, on the agent ``node_id``."""
        return CameraInfo(
            camera_serial=self.camera_serial,
            node_id=node_id,
            resolution=self.resolution,
            width=self.width,
            height=self.height,
            fps_nominal=self.fps,
            encoding=self.encoding,
            factory_conf_text=self.factory_conf,
        )


@dataclass(frozen=True, kw_only=True)
class AgentStatusReply:
    """The ``result`` of an agent's ``ok`` reply to ``status``."""

    cameras_info: tuple[AgentCameraInfo, ...]
    status: AgentStatus | None = None

    def camera(self, serial: int) -> AgentCameraInfo | None:
        return next((c for c in self.cameras_info if c.camera_serial == serial), None)

    @classmethod
    def from_json(cls, result: object, *, node_id: str | None = None) -> AgentStatusReply:
        """Check ``result``; with ``node_id`` (rig.toml's name of the agent), a ``status`` of
        another node is refused: rig.toml points at the wrong agent."""
        if not isinstance(result, dict):
            raise _bad("result", result, "a JSON object")
        entries = _require(result, "cameras_info", "")
        if not isinstance(entries, list) or not 1 <= len(entries) <= MAX_CAMERAS_PER_AGENT:
            raise _bad(
                "cameras_info",
                entries,
                f"a list of 1 to {MAX_CAMERAS_PER_AGENT} objects, one per camera of the agent",
            )
        infos = tuple(
            AgentCameraInfo.from_json(e, f"cameras_info[{i}]") for i, e in enumerate(entries)
        )
        seen: set[int] = set()
        for i, info in enumerate(infos):
            if info.camera_serial in seen:
                raise AgentReplyError(
                    f"cameras_info[{i}].camera_serial",
                    f"lists camera {info.camera_serial} twice (cameras_info[{i}] again)",
                )
            seen.add(info.camera_serial)
        status = None
        if result.get("status") is not None:
            status = _status(result["status"])
            if node_id is not None and status.node_id != node_id:
                raise AgentReplyError(
                    "status.node_id",
                    f"has status.node_id = {_show(status.node_id)}, but rig.toml names this "
                    f"agent {node_id!r}; node_id in node.toml, frames and status must equal "
                    "rig.toml's",
                )
        return cls(cameras_info=infos, status=status)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"cameras_info": [c.to_json() for c in self.cameras_info]}
        if self.status is not None:
            out["status"] = self.status.to_json()
        return out


def _status(obj: object) -> AgentStatus:
    """An agent status message's JSON body (as published), checked with the message's own
    decoders; their errors are reported under ``status``."""
    if not isinstance(obj, dict):
        raise _bad("status", obj, "an agent status object (or absent)")
    for key in ("node_id", "sent_unix_ns", "status_seq", "software_version", "ptp", "cameras"):
        _require(obj, key, "status")
    if not isinstance(obj["ptp"], dict):
        raise _bad("status.ptp", obj["ptp"], "an object")
    for key in ("state", "master_offset_ns", "gm_present"):
        _require(obj["ptp"], key, "status.ptp")
    if not isinstance(obj["cameras"], list):
        raise _bad("status.cameras", obj["cameras"], "a list of camera status objects")
    for i, cam in enumerate(obj["cameras"]):
        if not isinstance(cam, dict):
            raise _bad(f"status.cameras[{i}]", cam, "an object")
        for key in _CAMERA_STATUS_FIELDS:
            _require(cam, key, f"status.cameras[{i}]")
    try:
        return AgentStatus(
            node_id=obj["node_id"],
            sent_unix_ns=obj["sent_unix_ns"],
            status_seq=obj["status_seq"],
            software_version=obj["software_version"],
            ptp=PtpState.from_json(obj["ptp"]),
            cameras=tuple(
                CameraStatus.from_json(c, f"status.cameras[{i}]")
                for i, c in enumerate(obj["cameras"])
            ),
        )
    except AgentReplyError:
        raise
    except MalformedMessageError as exc:
        raise AgentReplyError("status", f"has an invalid status: {exc}") from None
