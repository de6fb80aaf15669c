"""The frame message (magic ``b"EGSF"``): one stereo frame of one camera, a 112-byte binary
header and the two images as raw buffers, never copied. The byte layout is in
``protocol/wire/__init__.py``'s docstring."""

from __future__ import annotations

import enum
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from protocol.safe_text import brief as _brief
from protocol.wire.checks import (
    FRAME_MAGIC,
    I64_MAX,
    I64_MIN,
    MAX_NODE_ID_BYTES,
    U63,
    ImageBuffer,
    MalformedMessageError,
    WirePart,
    as_buffer,
    check_int,
    check_node_id,
    check_prefix,
    flat_bytes,
)

FRAME_WIRE_VERSION = 1
MAX_FRAME_BYTES = 64 * 1024 * 1024  # per image; HD1200 raw BGR is 6.9 MB
MAX_IMAGE_SIDE_PX = 8192


class ImageTooLargeError(MalformedMessageError):
    """A frame whose image is larger than the receiver's ``max_image_bytes`` (rig.toml): a
    sender configured for bigger images than the rig was sized for, counted on its own."""


_FRAME_HEADER = struct.Struct("<4sHHQQQqqqQQHHBBBB32s")
FRAME_HEADER_BYTES = _FRAME_HEADER.size  # 112


class Encoding(str, enum.Enum):  # noqa: UP042 (StrEnum is 3.11; the edge runs 3.10)
    """How each image of a frame message is encoded. The value is the name used in files.

    A str whose ``str()`` and format are its value, as an ``enum.StrEnum``'s are; StrEnum itself
    is Python 3.11, and the edge also runs on 3.10 (JetPack)."""

    JPEG = "jpeg"
    RAW_BGR8 = "raw_bgr8"  # height * width * 3 bytes, BGR, row-major

    def __str__(self) -> str:
        return str.__str__(self)

    def __format__(self, format_spec: str) -> str:
        return str.__format__(self, format_spec)


_ENCODING_CODE = {Encoding.JPEG: 1, Encoding.RAW_BGR8: 2}
_CODE_ENCODING = {code: enc for enc, code in _ENCODING_CODE.items()}


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
        check_node_id(self.node_id, what)
        for name in ("camera_serial", "frame_index", "seq"):
            value = check_int(getattr(self, name), f"{what} {name}", 0, U63 - 1)
            object.__setattr__(self, name, value)
        for name in ("capture_unix_ns", "host_receive_unix_ns", "ptp_offset_ns"):
            value = check_int(getattr(self, name), f"{what} {name}", I64_MIN, I64_MAX)
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
            value = check_int(getattr(self, name), f"{what} {name}", 1, MAX_IMAGE_SIDE_PX)
            object.__setattr__(self, name, value)
        for side in ("left", "right"):
            view = flat_bytes(getattr(self, side), f"{what} {side} image")
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
    def from_parts(
        cls, parts: Sequence[WirePart], *, max_image_bytes: int = MAX_FRAME_BYTES
    ) -> FrameMessage:
        """Decode ``recv_multipart()`` output (bytes, or ``zmq.Frame`` with ``copy=False``).

        The image buffers of the result are views of ``parts[1]`` and ``parts[2]``, not copies.
        An image over ``max_image_bytes`` (the rig's limit) raises ``ImageTooLargeError``.
        """
        n_parts = len(parts)
        if n_parts == 0:
            raise MalformedMessageError("frame message has 0 parts, expected 3")
        header = as_buffer(parts[0], "frame header")
        check_prefix(header, FRAME_MAGIC, FRAME_WIRE_VERSION, "frame")
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
            if claimed > max_image_bytes:
                raise ImageTooLargeError(
                    f"frame of camera {camera_serial}: its {side} image is {claimed} bytes, above "
                    f"the rig's max_image_bytes = {max_image_bytes}; lower the camera's "
                    "resolution, use jpeg, or raise max_image_bytes in rig.toml"
                )
            buf = as_buffer(part, f"frame {side} image")
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


def _nbytes(buf: ImageBuffer) -> int:
    return len(buf) if isinstance(buf, bytes) else flat_bytes(buf, "image").nbytes
