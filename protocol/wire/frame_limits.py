"""The largest legal frame message and message part, from the wire's limits and the largest image.

A socket that receives frames is sized by ``frame_part_max_bytes`` (its ``MAXMSGSIZE``: a peer
that sends a bigger part is dropped before it is buffered); a queue slot, and rig.toml's buffer
checks, by ``frame_message_max_bytes`` (the header and two images). Both take the rig's
``max_image_bytes``, whose default is ``LARGEST_IMAGE_BYTES``.
"""

from __future__ import annotations

from protocol.wire.checks import MAX_JSON_BYTES, MAX_NODE_ID_BYTES
from protocol.wire.frame import FRAME_HEADER_BYTES

LARGEST_IMAGE_BYTES = 1920 * 1200 * 3  # raw_bgr8 at HD1200, the largest ZED X mode


def frame_part_max_bytes(max_image_bytes: int = LARGEST_IMAGE_BYTES) -> int:
    """MAXMSGSIZE of a socket that receives frames: its largest legal part (an image, the
    frame header or an agent status JSON)."""
    return max(max_image_bytes, MAX_JSON_BYTES + 16, FRAME_HEADER_BYTES + MAX_NODE_ID_BYTES)


def frame_message_max_bytes(max_image_bytes: int = LARGEST_IMAGE_BYTES) -> int:
    """The largest legal frame message: header and two images (what one queue slot can hold)."""
    return FRAME_HEADER_BYTES + MAX_NODE_ID_BYTES + 2 * max_image_bytes
