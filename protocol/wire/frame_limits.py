"""The largest legal frame message and message part, from the wire's limits and the largest image.

A socket that receives frames is sized by ``frame_part_max_bytes`` (its ``MAXMSGSIZE``: a peer
that sends a bigger part is dropped before it is buffered); a queue slot, and rig.toml's buffer
checks, by ``frame_message_max_bytes`` (the header and two images). Both take the rig's
``max_image_bytes``, whose default is ``LARGEST_IMAGE_BYTES``.

libzmq applies ``MAXMSGSIZE`` to a part as it arrives on the wire, and over CURVE each part
arrives inside a MESSAGE command that is ``CURVE_MESSAGE_OVERHEAD_BYTES`` longer than the part,
so the socket limit is the largest legal part plus that overhead: with the bare part size a
CURVE link refuses the largest legal image (and libzmq then drops the link). The image limit
itself is exact where frames are decoded (``FrameMessage.from_parts(max_image_bytes=...)``).
"""

from __future__ import annotations

from protocol.wire.checks import MAX_JSON_BYTES, MAX_NODE_ID_BYTES
from protocol.wire.frame import FRAME_HEADER_BYTES

LARGEST_IMAGE_BYTES = 1920 * 1200 * 3  # raw_bgr8 at HD1200, the largest ZED X mode
# A CURVE MESSAGE command around each part (RFC 26): the name's length byte and "MESSAGE" (8),
# the short nonce (8), the box's MAC (16) and the flags byte inside the box (1). Measured with
# libzmq 4.3: a part of N bytes passes MAXMSGSIZE = N + 33 and is refused at N + 32
# (tests/capture_agent/test_frame_size_limit.py).
CURVE_MESSAGE_OVERHEAD_BYTES = 1 + len(b"MESSAGE") + 8 + 16 + 1


def frame_part_max_bytes(max_image_bytes: int = LARGEST_IMAGE_BYTES) -> int:
    """MAXMSGSIZE of a socket that receives frames: its largest legal part (an image, the
    frame header or an agent status JSON) as it arrives over CURVE."""
    largest = max(max_image_bytes, MAX_JSON_BYTES + 16, FRAME_HEADER_BYTES + MAX_NODE_ID_BYTES)
    return largest + CURVE_MESSAGE_OVERHEAD_BYTES


def frame_message_max_bytes(max_image_bytes: int = LARGEST_IMAGE_BYTES) -> int:
    """The largest legal frame message: header and two images (what one queue slot can hold)."""
    return FRAME_HEADER_BYTES + MAX_NODE_ID_BYTES + 2 * max_image_bytes
