"""How stereo frames are encoded on the wire and in the session file (the contract both ends share).

Images on the capture path are BGR, 8-bit, ``(height, width, 3)`` (see docs/capture.md). Two
encodings exist:

- ``jpeg``: one baseline JPEG per side (``cv2.imencode``), decoded back to BGR by
  ``cv2.imdecode``; a 1920x1200 frame at quality 90 is about 0.3 to 0.6 MB instead of 6.9 MB.
  Colour is kept at full resolution (4:4:4 chroma, not OpenCV's default 4:2:0): wand detection
  reads each pixel's own colour, and with 4:2:0 its sphere centres were 10x worse (0.3 px median
  against 0.03 px on the sim), which alone would break the calibration's 0.3 px goal;
- ``raw_bgr8``: the C-contiguous bytes of the array, row-major, B G R per pixel.

Example::

    pair = encode_pair(left_bgr, right_bgr, "jpeg", jpeg_quality=90)
    left = decode_image(pair.left, pair.encoding, pair.width, pair.height)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from protocol.errors import UserError

ENCODINGS = ("jpeg", "raw_bgr8")


class EncodeError(UserError, ValueError):
    """An image or an encoding option that cannot be used; the message says which and why."""


@dataclass(frozen=True, kw_only=True)
class EncodedPair:
    """Both images of one stereo frame, encoded. ``width``/``height`` are in pixels, per side."""

    encoding: str
    width: int
    height: int
    left: bytes
    right: bytes

    def __post_init__(self) -> None:
        require_encoding(self.encoding)
        if self.width <= 0 or self.height <= 0:
            raise EncodeError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def nbytes(self) -> int:
        return len(self.left) + len(self.right)


def require_encoding(encoding: str) -> str:
    if encoding not in ENCODINGS:
        raise EncodeError(f"unknown encoding {encoding!r}; choose one of {', '.join(ENCODINGS)}")
    return encoding


def require_jpeg_quality(quality: int) -> int:
    if isinstance(quality, bool) or not isinstance(quality, int | np.integer):
        raise EncodeError(f"jpeg_quality={quality!r} must be an integer from 1 to 100")
    if not 1 <= int(quality) <= 100:
        raise EncodeError(f"jpeg_quality={quality} must be from 1 to 100 (90 is a good default)")
    return int(quality)


def _require_bgr(image: np.ndarray, name: str) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise EncodeError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise EncodeError(
            f"{name} must be (height, width, 3) uint8 BGR, got shape {image.shape} {image.dtype}"
        )
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise EncodeError(f"{name} is empty: shape {image.shape}")
    return image


def encode_image(image_bgr: np.ndarray, encoding: str, jpeg_quality: int = 90) -> bytes:
    """One (H, W, 3) uint8 BGR image -> bytes in ``encoding``."""
    _require_bgr(image_bgr, "image")
    if require_encoding(encoding) == "raw_bgr8":
        return np.ascontiguousarray(image_bgr).tobytes()
    quality = require_jpeg_quality(jpeg_quality)
    params = [
        int(cv2.IMWRITE_JPEG_QUALITY),
        quality,
        int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR),
        int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
    ]
    ok, buf = cv2.imencode(".jpg", image_bgr, params)
    if not ok:  # pragma: no cover - OpenCV fails only on unsupported input, checked above
        raise EncodeError(f"OpenCV could not JPEG-encode an image of shape {image_bgr.shape}")
    return buf.tobytes()


def encode_pair(
    left_bgr: np.ndarray, right_bgr: np.ndarray, encoding: str, jpeg_quality: int = 90
) -> EncodedPair:
    """Encode both sides of a stereo frame; both must be (H, W, 3) uint8 BGR of the same size."""
    _require_bgr(left_bgr, "left image")
    _require_bgr(right_bgr, "right image")
    if left_bgr.shape != right_bgr.shape:
        raise EncodeError(
            f"left and right images differ in size: {left_bgr.shape} vs {right_bgr.shape}"
        )
    require_encoding(encoding)
    if encoding == "jpeg":
        require_jpeg_quality(jpeg_quality)
    height, width = left_bgr.shape[:2]
    return EncodedPair(
        encoding=encoding,
        width=int(width),
        height=int(height),
        left=encode_image(left_bgr, encoding, jpeg_quality),
        right=encode_image(right_bgr, encoding, jpeg_quality),
    )


def decode_image(
    buf: bytes | bytearray | memoryview, encoding: str, width: int, height: int
) -> np.ndarray:
    """Bytes in ``encoding`` -> (height, width, 3) uint8 BGR; the size is checked.

    A ``raw_bgr8`` image is a read-only view of ``buf`` when ``buf`` is immutable (no copy).
    """
    require_encoding(encoding)
    if width <= 0 or height <= 0:
        raise EncodeError(f"image size must be positive, got {width}x{height}")
    data = np.frombuffer(buf, dtype=np.uint8)
    if encoding == "raw_bgr8":
        expected = width * height * 3
        if data.size != expected:
            raise EncodeError(
                f"raw_bgr8 buffer has {data.size} bytes; {width}x{height}x3 needs {expected}"
            )
        return data.reshape(height, width, 3)
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise EncodeError(f"not a decodable JPEG ({data.size} bytes)")
    if image.shape != (height, width, 3):
        raise EncodeError(
            f"JPEG is {image.shape[1]}x{image.shape[0]}, but the header says {width}x{height}"
        )
    return image
