"""Wire messages between capture agents, the recorder and the control tools.

Every message has one encoder and one decoder here. Nothing from the network is ever unpickled or
``eval``-ed: frames are a fixed binary header plus raw buffers, everything else is UTF-8 JSON.

Sockets (the whole agent-recorder contract: ``docs/capture.md``, "Writing an agent")
-------------------------------------------------------------------------------------
- Agent ``PUB`` (the agent binds ``frames_bind``) -> recorder ``SUB`` (connects to every agent's
  ``frames`` in rig.toml, subscribes to everything): frame messages (3 parts) and agent status
  messages (1 part), interleaved on one socket. The receiver calls ``decode_published(parts)``,
  which dispatches on the 4-byte magic that starts the first part.
- Control, ``REQ``/``REP`` (or ``DEALER``/``ROUTER``): one ``ControlRequest`` part, answered by one
  ``ControlReply`` part. Every agent binds a ``REP`` socket (``control_bind``) that the recorder
  connects to; the recorder binds its own ``REP`` for the control tools.
- Every link is CURVE-encrypted, the binding side the CURVE server with an allow-list of client
  keys; plaintext only where the configs say ``insecure = true``.
- ``node_id`` in frames and status messages must equal the agent's ``node_id`` in rig.toml.

Frame message (magic ``b"EGSF"``), a ZeroMQ multipart message of exactly 3 parts
----------------------------------------------------------------------------------
Part 0 is a 112-byte little-endian header (``struct`` format ``"<4sHHQQQqqqQQHHBBBB32s"``, no
implicit padding; every 8-byte field sits on an 8-byte boundary)::

    offset size type   field                  meaning
    0      4    bytes  magic                  b"EGSF"
    4      2    u16    wire_version           1 (FRAME_WIRE_VERSION)
    6      2    u16    header_bytes           112, the size of this header
    8      8    u64    seq                    per publisher, +1 per frame message; a gap is a drop
    16     8    u64    camera_serial          ZED serial number
    24     8    u64    frame_index            per camera, from 0
    32     8    i64    capture_unix_ns        frame time, Unix ns, PTP-disciplined system clock
    40     8    i64    host_receive_unix_ns   agent host clock when the frame came off the camera
    48     8    i64    ptp_offset_ns          PTP master offset when the frame was taken
    56     8    u64    left_bytes             length of part 1
    64     8    u64    right_bytes            length of part 2
    72     2    u16    width                  pixels, 1..8192, both images
    74     2    u16    height                 pixels, 1..8192, both images
    76     1    u8     encoding               1 = jpeg, 2 = raw_bgr8
    77     1    u8     ptp_locked             0 or 1
    78     1    u8     node_id_bytes          1..32, length of the UTF-8 node id
    79     1    u8     reserved               0
    80     32   bytes  node_id                UTF-8, padded with NUL bytes to 32

``frame_index`` only increases while a camera stays open; after a reopen it may restart at 0 (the
recorder records a reconnect, not a loss). ``seq`` going backwards means the agent restarted.
``ptp_offset_ns`` has linuxptp's sign: this node's clock minus the grandmaster's (0 if unknown).
``width``, ``height`` and ``encoding`` equal the camera's ``cameras_info`` entry (below).

Part 1 is the left image, part 2 the right image, each sent and received without a copy
(``send_multipart(msg.to_parts(), copy=False)`` / ``recv_multipart(copy=False)``). ``jpeg`` is a
complete JPEG file (starts with ``FF D8``) that decodes to BGR; ``raw_bgr8`` is exactly
``height * width * 3`` bytes, 8-bit BGR, row-major (OpenCV's ``(height, width, 3)`` array).
Unsigned fields carry values below 2**63, so every field fits an int64 (HDF5, numpy).

Agent status message (magic ``b"EGSH"``), 1 part, about once a second per agent
---------------------------------------------------------------------------------
``b"EGSH"`` + u16 little-endian wire version (1, ``STATUS_WIRE_VERSION``) + a UTF-8 JSON object::

    {"node_id": "node-a", "sent_unix_ns": 1700000000000000000, "status_seq": 42,
     "software_version": "0.1.0",
     "ptp": {"state": "locked", "master_offset_ns": -12, "gm_present": true},
     "cameras": [{"camera_serial": 40123456, "state": "streaming", "fps_measured": 29.97,
                  "frames_captured": 1200, "frames_dropped": 0, "frames_published": 1200,
                  "queue_depth": 1, "reopen_count": 0,
                  "last_capture_unix_ns": 1699999999990000000, "error": null}]}

``status_seq`` is the status messages' own counter, independent of the frames' ``seq``. Every
field is required; ``master_offset_ns``, ``gm_present``, ``last_capture_unix_ns`` and ``error``
are nullable. ``ptp.state`` is one of ``PTP_STATES``, a camera's ``state`` one of
``CAMERA_STATES`` (meanings in docs/capture.md). The recorder counts an agent gone after
``agent_timeout_s`` (rig.toml, default 3 s) without a status message.

Control messages, 1 part, a UTF-8 JSON object
---------------------------------------------
Request: ``{"egosurg": "control", "version": 1, "verb": "start", "args": {...},
"request_id": "..."}``; verbs are ``CONTROL_VERBS``. Reply: ``{"egosurg": "reply", "version": 1,
"ok": false, "result": {}, "error": "PTP is unlocked on node-b; ...", "request_id": "..."}``,
echoing the request's ``request_id`` (1..``MAX_REQUEST_ID_CHARS`` characters, no control
characters); ``error`` is null exactly when ``ok`` is true. A ``REP`` socket answers every
request, also one it cannot decode (``ok: false`` with ``request_id`` ""). An agent answers ``status`` and
``heartbeat`` with ``ok: true`` and ``start``/``stop`` with ``ok: false``; its ``status`` result
is ``{"cameras_info": [{"camera_serial", "resolution", "width", "height", "fps", "encoding",
"factory_conf"}, ...], "status": {...optional, a status message's body}}``, checked by
``protocol/agent_info.py`` (every entry field required, ``factory_conf`` text or null).

Versioning
----------
The magic and the version (bytes 0..5 of a binary message, ``egosurg``/``version`` of a JSON one)
keep their place in every version. Any change to a binary layout, a field's meaning or unit, or a
required JSON field bumps the version; there are no optional binary fields. A receiver reads the
version before anything else and rejects one it does not know with ``UnknownVersionError``. JSON
messages may gain fields without a version bump: a receiver ignores fields it does not know.

What is rejected (``MalformedMessageError``, a ``ValueError``)
--------------------------------------------------------------
Wrong magic; unknown version (``UnknownVersionError``); wrong part count; a header of the wrong
size; lengths in the header that differ from the buffers; width or height outside 1..8192;
``raw_bgr8`` not ``width * height * 3`` bytes; ``jpeg`` not starting with ``FF D8``; an image above
``MAX_FRAME_BYTES``; a node id that is empty, over 32 bytes or not UTF-8; negative or out-of-range
integers; non-zero reserved or padding bytes; non-UTF-8 or non-JSON bodies, non-object JSON,
missing or mistyped fields, unknown states or verbs; JSON bodies above ``MAX_JSON_BYTES``. The same
checks run when a message is constructed, so a sender cannot build what a receiver would refuse.
Receivers count and log these errors and keep running; decoders raise nothing else on bad input.
"""

from __future__ import annotations

import enum
import json
import math
import struct
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, TypeAlias

import numpy as np

from protocol.errors import UserError
from protocol.safe_text import brief as _brief
from protocol.safe_text import unsafe_character

if TYPE_CHECKING:
    import zmq


class MalformedMessageError(UserError, ValueError):
    """A message that does not follow the wire spec in this module's docstring."""


class UnknownVersionError(MalformedMessageError):
    """A well-formed EgoSurg message of a wire version this code does not speak."""


FRAME_MAGIC = b"EGSF"
STATUS_MAGIC = b"EGSH"
FRAME_WIRE_VERSION = 1
STATUS_WIRE_VERSION = 1
CONTROL_WIRE_VERSION = 1

MAX_FRAME_BYTES = 64 * 1024 * 1024  # per image; HD1200 raw BGR is 6.9 MB
MAX_JSON_BYTES = 1024 * 1024  # status and control bodies
MAX_IMAGE_SIDE_PX = 8192
MAX_NODE_ID_BYTES = 32
MAX_REQUEST_ID_CHARS = 128  # a uuid4 hex is 32

_FRAME_HEADER = struct.Struct("<4sHHQQQqqqQQHHBBBB32s")
FRAME_HEADER_BYTES = _FRAME_HEADER.size  # 112
_PREFIX = struct.Struct("<4sH")  # magic + version, shared by both binary message kinds
_U63 = 2**63  # unsigned wire integers stay below this so they fit an int64
_I64_MIN, _I64_MAX = -(2**63), 2**63 - 1

PTP_STATES = ("locked", "unlocked", "no_ptp4l", "no_pmc", "disabled")
CAMERA_STATES = ("streaming", "stalled", "reopening", "closed", "error")
CONTROL_VERBS = ("start", "stop", "status", "heartbeat")

# What an image buffer may be when a message is built. After construction it is ``bytes`` (kept
# as given) or a flat unsigned-byte ``memoryview`` over the caller's memory: never a copy.
ImageBuffer: TypeAlias = "bytes | bytearray | memoryview | np.ndarray"
# One received part: bytes, a buffer, or a ``zmq.Frame`` from ``recv_multipart(copy=False)``.
WirePart: TypeAlias = "bytes | bytearray | memoryview | np.ndarray | zmq.Frame"


class Encoding(enum.StrEnum):
    """How each image of a frame message is encoded. The value is the name used in files."""

    JPEG = "jpeg"
    RAW_BGR8 = "raw_bgr8"  # height * width * 3 bytes, BGR, row-major


_ENCODING_CODE = {Encoding.JPEG: 1, Encoding.RAW_BGR8: 2}
_CODE_ENCODING = {code: enc for enc, code in _ENCODING_CODE.items()}


# --------------------------------------------------------------------------------------------
# Frame messages
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class FrameMessage:
    """One stereo frame of one camera, as published by a capture agent.

    ``left``/``right`` are never copied: ``to_parts()`` hands them to ZeroMQ as given and
    ``from_parts()`` keeps views of the received frames, so ``np.frombuffer(msg.left, np.uint8)``
    reads the network buffer in place.
    """

    node_id: str
    camera_serial: int
    frame_index: int
    seq: int
    capture_unix_ns: int
    host_receive_unix_ns: int
    ptp_offset_ns: int
    ptp_locked: bool
    encoding: Encoding
    width: int
    height: int
    left: ImageBuffer = field(repr=False)
    right: ImageBuffer = field(repr=False)

    # Buffers may be writable memoryviews, which cannot be hashed; a message is a value to send,
    # not a key.
    __hash__: ClassVar[None] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        what = "frame message"
        _check_node_id(self.node_id, what)
        for name in ("camera_serial", "frame_index", "seq"):
            value = _check_int(getattr(self, name), f"{what} {name}", 0, _U63 - 1)
            object.__setattr__(self, name, value)
        for name in ("capture_unix_ns", "host_receive_unix_ns", "ptp_offset_ns"):
            value = _check_int(getattr(self, name), f"{what} {name}", _I64_MIN, _I64_MAX)
            object.__setattr__(self, name, value)
        if not isinstance(self.ptp_locked, bool | np.bool_):
            raise MalformedMessageError(
                f"{what} ptp_locked={_brief(self.ptp_locked)} must be a bool (True or False)"
            )
        object.__setattr__(self, "ptp_locked", bool(self.ptp_locked))
        try:
            encoding = Encoding(self.encoding)
        except ValueError:
            valid = ", ".join(e.value for e in Encoding)
            raise MalformedMessageError(
                f"{what} encoding {_brief(self.encoding)} is unknown; valid encodings: {valid}"
            ) from None
        object.__setattr__(self, "encoding", encoding)
        for name in ("width", "height"):
            value = _check_int(getattr(self, name), f"{what} {name}", 1, MAX_IMAGE_SIDE_PX)
            object.__setattr__(self, name, value)
        for side in ("left", "right"):
            view = _flat_bytes(getattr(self, side), f"{what} {side} image")
            _check_image(view, side, encoding, self.width, self.height)
            if not isinstance(getattr(self, side), bytes):
                object.__setattr__(self, side, view)

    @property
    def left_bytes(self) -> int:
        return _nbytes(self.left)

    @property
    def right_bytes(self) -> int:
        return _nbytes(self.right)

    def header(self) -> bytes:
        """The 112-byte header (part 0)."""
        node = self.node_id.encode("utf-8")
        return _FRAME_HEADER.pack(
            FRAME_MAGIC,
            FRAME_WIRE_VERSION,
            FRAME_HEADER_BYTES,
            self.seq,
            self.camera_serial,
            self.frame_index,
            self.capture_unix_ns,
            self.host_receive_unix_ns,
            self.ptp_offset_ns,
            self.left_bytes,
            self.right_bytes,
            self.width,
            self.height,
            _ENCODING_CODE[self.encoding],
            int(self.ptp_locked),
            len(node),
            0,
            node,
        )

    def to_parts(self) -> list[ImageBuffer]:
        """``[header, left, right]`` for ``sock.send_multipart(parts, copy=False)``."""
        return [self.header(), self.left, self.right]

    @classmethod
    def from_parts(cls, parts: Sequence[WirePart]) -> FrameMessage:
        """Decode ``recv_multipart()`` output (bytes, or ``zmq.Frame`` with ``copy=False``).

        The image buffers of the result are views of ``parts[1]`` and ``parts[2]``, not copies.
        """
        n_parts = len(parts)
        if n_parts == 0:
            raise MalformedMessageError("frame message has 0 parts, expected 3")
        header = _as_buffer(parts[0], "frame header")
        _check_prefix(header, FRAME_MAGIC, FRAME_WIRE_VERSION, "frame")
        if n_parts != 3:
            raise MalformedMessageError(
                f"frame message has {n_parts} parts, expected 3 (header, left image, right image)"
            )
        if len(header) != FRAME_HEADER_BYTES:
            raise MalformedMessageError(
                f"frame header is {len(header)} bytes, expected {FRAME_HEADER_BYTES} "
                f"for wire version {FRAME_WIRE_VERSION} (truncated or padded header)"
            )
        (
            _magic,
            _version,
            header_bytes,
            seq,
            camera_serial,
            frame_index,
            capture_unix_ns,
            host_receive_unix_ns,
            ptp_offset_ns,
            left_bytes,
            right_bytes,
            width,
            height,
            encoding_code,
            ptp_locked,
            node_id_bytes,
            reserved,
            node_raw,
        ) = _FRAME_HEADER.unpack(header)
        if header_bytes != FRAME_HEADER_BYTES:
            raise MalformedMessageError(
                f"frame header says it is {header_bytes} bytes, but version "
                f"{FRAME_WIRE_VERSION} headers are {FRAME_HEADER_BYTES}"
            )
        if reserved != 0:
            raise MalformedMessageError(f"frame header reserved byte is {reserved}, expected 0")
        if encoding_code not in _CODE_ENCODING:
            valid = ", ".join(f"{c} ({e.value})" for c, e in _CODE_ENCODING.items())
            raise MalformedMessageError(
                f"frame header encoding code {encoding_code} is unknown; valid codes: {valid}"
            )
        if ptp_locked not in (0, 1):
            raise MalformedMessageError(f"frame header ptp_locked byte is {ptp_locked}, not 0/1")
        if not 1 <= node_id_bytes <= MAX_NODE_ID_BYTES:
            raise MalformedMessageError(
                f"frame header node_id length is {node_id_bytes}, expected 1..{MAX_NODE_ID_BYTES}"
            )
        if node_raw[node_id_bytes:].strip(b"\0"):
            raise MalformedMessageError("frame header node_id padding is not all NUL bytes")
        node_bytes = node_raw[:node_id_bytes]
        try:
            node_id = node_bytes.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise MalformedMessageError(
                f"frame header node_id {_brief(node_bytes)} is not valid UTF-8 ({exc.reason})"
            ) from None
        images = []
        for side, claimed, part in (
            ("left", left_bytes, parts[1]),
            ("right", right_bytes, parts[2]),
        ):
            if claimed > MAX_FRAME_BYTES:
                raise MalformedMessageError(
                    f"frame header says the {side} image is {claimed} bytes, above the "
                    f"{MAX_FRAME_BYTES}-byte limit (MAX_FRAME_BYTES)"
                )
            buf = _as_buffer(part, f"frame {side} image")
            if len(buf) != claimed:
                raise MalformedMessageError(
                    f"frame header says the {side} image is {claimed} bytes, "
                    f"but part {1 if side == 'left' else 2} holds {len(buf)} bytes"
                )
            images.append(buf)
        return cls(
            node_id=node_id,
            camera_serial=camera_serial,
            frame_index=frame_index,
            seq=seq,
            capture_unix_ns=capture_unix_ns,
            host_receive_unix_ns=host_receive_unix_ns,
            ptp_offset_ns=ptp_offset_ns,
            ptp_locked=bool(ptp_locked),
            encoding=_CODE_ENCODING[encoding_code],
            width=width,
            height=height,
            left=images[0],
            right=images[1],
        )


def _check_image(view: memoryview, side: str, encoding: Encoding, width: int, height: int) -> None:
    n = len(view)
    if n > MAX_FRAME_BYTES:
        raise MalformedMessageError(
            f"frame message {side} image is {n} bytes, above the {MAX_FRAME_BYTES}-byte limit "
            "(MAX_FRAME_BYTES); lower the resolution or use jpeg"
        )
    if encoding is Encoding.RAW_BGR8:
        expected = width * height * 3
        if n != expected:
            raise MalformedMessageError(
                f"frame message {side} image is {n} bytes, but raw_bgr8 at {width}x{height} "
                f"needs width*height*3 = {expected}"
            )
    elif n < 2 or view[0] != 0xFF or view[1] != 0xD8:
        start = bytes(view[:2]).hex(" ").upper() or "nothing"
        raise MalformedMessageError(
            f"frame message {side} image is not a JPEG: it starts with {start}, not FF D8"
        )


def _flat_bytes(buf: object, what: str) -> memoryview:
    """A 1-D unsigned-byte view of ``buf`` without copying; rejects non-buffers."""
    try:
        view = memoryview(buf)  # type: ignore[arg-type]
    except TypeError:
        raise MalformedMessageError(
            f"{what} is a {type(buf).__name__}, expected bytes or a buffer (memoryview, numpy)"
        ) from None
    if not view.c_contiguous:
        raise MalformedMessageError(
            f"{what} is not C-contiguous; pass np.ascontiguousarray(image) so it can be sent as is"
        )
    return view if view.format == "B" and view.ndim == 1 else view.cast("B")


def _nbytes(buf: ImageBuffer) -> int:
    return len(buf) if isinstance(buf, bytes) else _flat_bytes(buf, "image").nbytes


def _as_buffer(part: object, what: str) -> bytes | memoryview:
    """A received part as ``bytes`` or a flat byte view; ``zmq.Frame`` via ``.buffer``."""
    if isinstance(part, bytes):
        return part
    if not isinstance(part, bytearray | memoryview) and hasattr(part, "buffer"):
        part = part.buffer  # zmq.Frame: a view of the message memory, not a copy
    return _flat_bytes(part, what)


def _check_prefix(buf: bytes | memoryview, magic: bytes, supported: int, kind: str) -> None:
    if len(buf) < _PREFIX.size:
        raise MalformedMessageError(
            f"{kind} message first part is {len(buf)} bytes, too short to hold the "
            f"{_PREFIX.size}-byte magic and version (truncated)"
        )
    got_magic, version = _PREFIX.unpack_from(buf)
    if got_magic != magic:
        raise MalformedMessageError(_magic_problem(got_magic, f"{kind} message", magic))
    _check_version(version, supported, f"{kind} message")


def _magic_problem(got: bytes, kind: str, expected: bytes) -> str:
    other = {FRAME_MAGIC: "a frame message", STATUS_MAGIC: "an agent status message"}.get(got)
    if other is not None:
        return (
            f"header magic {_brief(got)} is {other}, not a {kind}; decode with decode_published()"
        )
    return (
        f"header magic {_brief(got)} is not an EgoSurg message (a {kind} starts with {expected!r})"
    )


def _check_version(version: object, supported: int, kind: str) -> None:
    if version == supported:
        return
    if isinstance(version, int) and not isinstance(version, bool) and version > supported:
        hint = "upgrade the receiver (recorder or control tool) to the sender's EgoSurg version"
    else:
        hint = (
            "upgrade the sender (capture agent or control tool) to the receiver's EgoSurg version"
        )
    raise UnknownVersionError(
        f"{kind} wire version {_brief(version)} is not supported by this receiver "
        f"(supports {supported}); {hint}"
    )


# --------------------------------------------------------------------------------------------
# Agent status
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class PtpState:
    """The agent's PTP state as read from linuxptp's ``pmc``."""

    state: str
    master_offset_ns: int | None = None
    gm_present: bool | None = None

    def __post_init__(self) -> None:
        _check_choice(self.state, "ptp state", PTP_STATES)
        if self.master_offset_ns is not None:
            offset = _check_int(self.master_offset_ns, "ptp master_offset_ns", _I64_MIN, _I64_MAX)
            object.__setattr__(self, "master_offset_ns", offset)
        if self.gm_present is not None and not isinstance(self.gm_present, bool):
            raise MalformedMessageError(
                f"ptp gm_present={_brief(self.gm_present)} must be true, false or null"
            )

    def to_json(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "master_offset_ns": self.master_offset_ns,
            "gm_present": self.gm_present,
        }

    @classmethod
    def from_json(cls, obj: object) -> PtpState:
        d = _require_object(obj, "agent status ptp")
        return cls(
            state=_get(d, "state", str, "agent status ptp"),
            master_offset_ns=_get(d, "master_offset_ns", int, "agent status ptp", nullable=True),
            gm_present=_get(d, "gm_present", bool, "agent status ptp", nullable=True),
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
        _check_choice(self.state, f"{where} state", CAMERA_STATES)
        for name in self._COUNTERS:
            value = _check_int(getattr(self, name), f"{where} {name}", 0, _U63 - 1)
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
            last = _check_int(
                self.last_capture_unix_ns, f"{where} last_capture_unix_ns", 0, _I64_MAX
            )
            object.__setattr__(self, "last_capture_unix_ns", last)
        if self.error is not None and not isinstance(self.error, str):
            raise MalformedMessageError(
                f"{where} error={_brief(self.error)} must be a string or null"
            )

    def to_json(self) -> dict[str, Any]:
        return {
            "camera_serial": self.camera_serial,
            "state": self.state,
            "fps_measured": self.fps_measured,
            "frames_captured": self.frames_captured,
            "frames_dropped": self.frames_dropped,
            "frames_published": self.frames_published,
            "queue_depth": self.queue_depth,
            "reopen_count": self.reopen_count,
            "last_capture_unix_ns": self.last_capture_unix_ns,
            "error": self.error,
        }

    @classmethod
    def from_json(cls, obj: object, where: str = "agent status camera") -> CameraStatus:
        d = _require_object(obj, where)
        kwargs: dict[str, Any] = {name: _get(d, name, int, where) for name in cls._COUNTERS}
        return cls(
            **kwargs,
            state=_get(d, "state", str, where),
            fps_measured=_get(d, "fps_measured", float, where),
            last_capture_unix_ns=_get(d, "last_capture_unix_ns", int, where, nullable=True),
            error=_get(d, "error", str, where, nullable=True),
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
        _check_node_id(self.node_id, "agent status")
        sent = _check_int(self.sent_unix_ns, "agent status sent_unix_ns", _I64_MIN, _I64_MAX)
        object.__setattr__(self, "sent_unix_ns", sent)
        status_seq = _check_int(self.status_seq, "agent status status_seq", 0, _U63 - 1)
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
        body = _dump_json(self.to_json(), "agent status")
        return [_PREFIX.pack(STATUS_MAGIC, STATUS_WIRE_VERSION) + body]

    @classmethod
    def from_parts(cls, parts: Sequence[WirePart]) -> AgentStatus:
        if len(parts) == 0:
            raise MalformedMessageError("agent status message has 0 parts, expected 1")
        buf = _as_buffer(parts[0], "agent status")
        _check_prefix(buf, STATUS_MAGIC, STATUS_WIRE_VERSION, "agent status")
        if len(parts) != 1:
            raise MalformedMessageError(f"agent status message has {len(parts)} parts, expected 1")
        d = _load_json_object(buf[_PREFIX.size :], "agent status")
        where = "agent status"
        cams = _get(d, "cameras", list, where)
        return cls(
            node_id=_get(d, "node_id", str, where),
            sent_unix_ns=_get(d, "sent_unix_ns", int, where),
            status_seq=_get(d, "status_seq", int, where),
            software_version=_get(d, "software_version", str, where),
            ptp=PtpState.from_json(_get(d, "ptp", dict, where)),
            cameras=tuple(
                CameraStatus.from_json(c, f"agent status cameras[{i}]") for i, c in enumerate(cams)
            ),
        )


def decode_published(parts: Sequence[WirePart]) -> FrameMessage | AgentStatus:
    """Decode anything an agent publishes, by the magic at the start of the first part."""
    if len(parts) == 0:
        raise MalformedMessageError("published message has 0 parts")
    first = _as_buffer(parts[0], "published message")
    if len(first) < 4:
        raise MalformedMessageError(
            f"published message first part is {len(first)} bytes, too short for a 4-byte magic"
        )
    magic = bytes(first[:4])
    if magic == FRAME_MAGIC:
        return FrameMessage.from_parts(parts)
    if magic == STATUS_MAGIC:
        return AgentStatus.from_parts(parts)
    raise MalformedMessageError(
        f"header magic {_brief(magic)} is not an EgoSurg message "
        f"(frames start with {FRAME_MAGIC!r}, agent status with {STATUS_MAGIC!r})"
    )


# --------------------------------------------------------------------------------------------
# Control
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class ControlRequest:
    """A control verb with its arguments, e.g. ``start`` with the session name and case data."""

    verb: str
    args: dict[str, Any] = field(default_factory=dict)
    request_id: str = field(default_factory=lambda: uuid.uuid4().hex)

    __hash__: ClassVar[None] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.verb not in CONTROL_VERBS:
            raise MalformedMessageError(
                f"control verb {_brief(self.verb)} is unknown; valid verbs: "
                f"{', '.join(CONTROL_VERBS)}"
            )
        _check_json_object(self.args, "control request args")
        _check_request_id(self.request_id, "control request")

    def to_bytes(self) -> bytes:
        return _dump_json(
            {
                "egosurg": "control",
                "version": CONTROL_WIRE_VERSION,
                "verb": self.verb,
                "args": self.args,
                "request_id": self.request_id,
            },
            "control request",
        )

    @classmethod
    def from_bytes(cls, data: WirePart) -> ControlRequest:
        d = _load_envelope(data, "control", "control request")
        return cls(
            verb=_get(d, "verb", str, "control request"),
            args=_get(d, "args", dict, "control request"),
            request_id=_get(d, "request_id", str, "control request"),
        )


@dataclass(frozen=True, kw_only=True)
class ControlReply:
    """The answer to one ``ControlRequest``: a result, or an error that says what to do."""

    ok: bool
    result: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    request_id: str

    __hash__: ClassVar[None] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if not isinstance(self.ok, bool):
            raise MalformedMessageError(f"control reply ok={_brief(self.ok)} must be true or false")
        _check_json_object(self.result, "control reply result")
        if self.ok and self.error is not None:
            raise MalformedMessageError(
                f"control reply is ok but carries error {_brief(self.error)}; error must be null"
            )
        if not self.ok and (not isinstance(self.error, str) or not self.error.strip()):
            raise MalformedMessageError(
                "control reply is not ok, so error must be a non-empty message saying what to do"
            )
        _check_request_id(self.request_id, "control reply", allow_empty=not self.ok)

    def to_bytes(self) -> bytes:
        return _dump_json(
            {
                "egosurg": "reply",
                "version": CONTROL_WIRE_VERSION,
                "ok": self.ok,
                "result": self.result,
                "error": self.error,
                "request_id": self.request_id,
            },
            "control reply",
        )

    @classmethod
    def from_bytes(cls, data: WirePart) -> ControlReply:
        d = _load_envelope(data, "reply", "control reply")
        return cls(
            ok=_get(d, "ok", bool, "control reply"),
            result=_get(d, "result", dict, "control reply"),
            error=_get(d, "error", str, "control reply", nullable=True),
            request_id=_get(d, "request_id", str, "control reply"),
        )


def _load_envelope(data: WirePart, kind: str, what: str) -> dict[str, Any]:
    d = _load_json_object(_as_buffer(data, what), what)
    got = d.get("egosurg")
    if got != kind:
        if got in ("control", "reply"):
            raise MalformedMessageError(
                f"{what}: message is an EgoSurg {_brief(got)} message, expected {kind!r}"
            )
        raise MalformedMessageError(
            f"{what}: JSON field 'egosurg' is {_brief(got)}, expected {kind!r}; "
            "this is not an EgoSurg control message"
        )
    if "version" not in d:
        raise MalformedMessageError(f"{what}: missing field 'version'")
    _check_version(d["version"], CONTROL_WIRE_VERSION, what)
    return d


def _check_request_id(request_id: object, what: str, *, allow_empty: bool = False) -> None:
    """A request id is 1..MAX_REQUEST_ID_CHARS characters without control characters. Only an
    error reply may carry an empty one: the answer to a request too broken to name its id."""
    if (
        not isinstance(request_id, str)
        or len(request_id) > MAX_REQUEST_ID_CHARS
        or (not request_id and not allow_empty)
        or unsafe_character(request_id) is not None
    ):
        raise MalformedMessageError(
            f"{what} request_id={_brief(request_id)} must be a string of 1..{MAX_REQUEST_ID_CHARS}"
            " characters without control characters"
            + (" (empty only in an error reply to an unreadable request)" if allow_empty else "")
        )


# --------------------------------------------------------------------------------------------
# Shared field checks
# --------------------------------------------------------------------------------------------


def _check_int(value: object, what: str, lo: int, hi: int) -> int:
    """``value`` as a plain ``int`` if it is an integer in ``lo..hi``; bools are not integers."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise MalformedMessageError(f"{what}={_brief(value)} must be an integer")
    number = int(value)
    if lo == 0 and number < 0:
        raise MalformedMessageError(f"{what}={number} must not be negative")
    if not lo <= number <= hi:
        raise MalformedMessageError(f"{what}={number} is outside {lo}..{hi}")
    return number


def _check_node_id(node_id: object, what: str) -> None:
    if not isinstance(node_id, str):
        raise MalformedMessageError(f"{what} node_id={_brief(node_id)} must be a string")
    try:
        raw = node_id.encode("utf-8")
    except UnicodeEncodeError:
        raise MalformedMessageError(
            f"{what} node_id={_brief(node_id)} cannot be encoded as UTF-8"
        ) from None
    if not 1 <= len(raw) <= MAX_NODE_ID_BYTES or "\0" in node_id:
        raise MalformedMessageError(
            f"{what} node_id={_brief(node_id)} must be 1..{MAX_NODE_ID_BYTES} UTF-8 bytes "
            "without NUL "
            f"(it is {len(raw)} bytes)"
        )


def _check_choice(value: object, what: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise MalformedMessageError(
            f"{what} {_brief(value)} is unknown; valid: {', '.join(choices)}"
        )


def _check_json_object(value: object, what: str) -> None:
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise MalformedMessageError(
            f"{what} must be a JSON object with string keys, got {_brief(value)}"
        )
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise MalformedMessageError(f"{what} cannot be sent as JSON: {exc}") from None


_JSON_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", bool: "true/false",
                    dict: "an object", list: "a list"}  # fmt: skip


def _get(d: Mapping[str, Any], key: str, kind: type, where: str, *, nullable: bool = False) -> Any:
    """``d[key]`` checked against a JSON type; missing keys are errors, extra keys are ignored."""
    if key not in d:
        raise MalformedMessageError(f"{where}: missing field {_brief(key)}")
    value = d[key]
    if value is None and nullable:
        return None
    if kind is float:  # JSON does not tell 30 from 30.0
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if not ok:
        expected = _JSON_TYPE_NAMES[kind] + (" or null" if nullable else "")
        raise MalformedMessageError(
            f"{where}: field {_brief(key)}={_brief(value)} must be {expected}"
        )
    return value


def _require_object(obj: object, where: str) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise MalformedMessageError(f"{where} must be a JSON object, got {type(obj).__name__}")
    return obj


def _dump_json(obj: dict[str, Any], what: str) -> bytes:
    body = json.dumps(obj, allow_nan=False, ensure_ascii=False, separators=(",", ":"))
    data = body.encode("utf-8")
    if len(data) > MAX_JSON_BYTES:
        raise MalformedMessageError(
            f"{what} JSON is {len(data)} bytes, above the {MAX_JSON_BYTES}-byte limit"
        )
    return data


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not valid JSON")


def _load_json_object(buf: bytes | memoryview, what: str) -> dict[str, Any]:
    if len(buf) > MAX_JSON_BYTES:
        raise MalformedMessageError(
            f"{what} JSON is {len(buf)} bytes, above the {MAX_JSON_BYTES}-byte limit"
        )
    try:
        text = bytes(buf).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MalformedMessageError(f"{what} body is not UTF-8 ({exc.reason})") from None
    try:
        obj = json.loads(text, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        raise MalformedMessageError(f"{what} body is not valid JSON: {exc}") from None
    if "\\u" in text:  # a "\ud800" escape decodes to a lone surrogate that cannot be re-sent
        try:
            json.dumps(obj, ensure_ascii=False).encode("utf-8")
        except (UnicodeEncodeError, RecursionError):
            raise MalformedMessageError(
                f"{what} body holds an unpaired UTF-16 surrogate escape (like \\ud800), "
                "which is not text"
            ) from None
    if not isinstance(obj, dict):
        raise MalformedMessageError(
            f"{what} body is a JSON {type(obj).__name__}, expected a JSON object"
        )
    return obj
