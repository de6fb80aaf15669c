"""JPEG and raw encoding of BGR stereo frames."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.errors import UserError
from protocol.images import EncodedPair, EncodeError, decode_image, encode_pair


def _pair(h: int = 60, w: int = 96) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:h, 0:w]
    left = np.stack([x * 255 // w, y * 255 // h, np.full_like(x, 40)], axis=-1).astype(np.uint8)
    right = np.ascontiguousarray(left[:, ::-1])
    return left, right


def test_raw_round_trip_is_exact():
    left, right = _pair()
    pair = encode_pair(left, right, "raw_bgr8")
    assert (pair.width, pair.height, pair.encoding) == (96, 60, "raw_bgr8")
    assert pair.nbytes == 2 * 96 * 60 * 3
    np.testing.assert_array_equal(decode_image(pair.left, "raw_bgr8", 96, 60), left)
    np.testing.assert_array_equal(decode_image(pair.right, "raw_bgr8", 96, 60), right)


def test_raw_accepts_non_contiguous_views():
    left, right = _pair()
    pair = encode_pair(left[:, ::-1], right[:, ::-1], "raw_bgr8")
    np.testing.assert_array_equal(decode_image(pair.left, "raw_bgr8", 96, 60), left[:, ::-1])


def test_jpeg_round_trip_keeps_bgr_order_and_is_smaller():
    left, right = _pair()
    left[:, :, 0] = 255  # strongly blue: a channel swap would show
    left[:, :, 2] = 0
    pair = encode_pair(left, right, "jpeg", jpeg_quality=95)
    assert pair.left[:2] == b"\xff\xd8"  # JPEG SOI marker
    assert pair.nbytes < 2 * left.nbytes
    out = decode_image(pair.left, "jpeg", 96, 60)
    assert out.shape == (60, 96, 3) and out.dtype == np.uint8
    assert np.abs(out.astype(int) - left.astype(int)).mean() < 4
    assert out[..., 0].mean() > 240 and out[..., 2].mean() < 15


def test_lower_quality_gives_fewer_bytes():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(120, 160, 3), dtype=np.uint8)
    high = encode_pair(img, img, "jpeg", jpeg_quality=95)
    low = encode_pair(img, img, "jpeg", jpeg_quality=20)
    assert len(low.left) < len(high.left)


@pytest.mark.parametrize("quality", [0, 101, 50.5, True])
def test_bad_quality_is_refused(quality):
    left, right = _pair()
    with pytest.raises(EncodeError, match="jpeg_quality"):
        encode_pair(left, right, "jpeg", jpeg_quality=quality)


def test_bad_inputs_are_refused_with_clear_errors():
    left, right = _pair()
    with pytest.raises(EncodeError, match=r"unknown encoding 'png'.*jpeg, raw_bgr8"):
        encode_pair(left, right, "png")
    with pytest.raises(EncodeError, match="differ in size"):
        encode_pair(left, right[:30], "jpeg")
    with pytest.raises(EncodeError, match=r"\(height, width, 3\) uint8"):
        encode_pair(left[..., 0], right[..., 0], "jpeg")
    with pytest.raises(EncodeError, match="uint8"):
        encode_pair(left.astype(np.float32), right.astype(np.float32), "raw_bgr8")
    with pytest.raises(EncodeError, match="needs 17280"):
        decode_image(b"\x00" * 10, "raw_bgr8", 96, 60)
    with pytest.raises(EncodeError, match="not a decodable JPEG"):
        decode_image(b"not a jpeg", "jpeg", 96, 60)
    pair = encode_pair(left, right, "jpeg")
    with pytest.raises(EncodeError, match="header says 90x60"):
        decode_image(pair.left, "jpeg", 90, 60)
    with pytest.raises(EncodeError):
        EncodedPair(encoding="jpeg", width=0, height=60, left=b"", right=b"")
    assert issubclass(EncodeError, UserError) and issubclass(EncodeError, ValueError)


def test_jpeg_keeps_colour_at_full_resolution():
    """4:4:4 chroma: wand detection reads each pixel's colour (4:2:0 made it 10x less accurate)."""
    import numpy as np

    from protocol.images import encode_pair

    img = np.random.default_rng(0).integers(0, 255, (64, 96, 3), dtype=np.uint8)
    jpg = encode_pair(img, img, "jpeg", 90).left
    sof = jpg.index(b"\xff\xc0")  # baseline frame header: per component, id and sampling byte
    n_components = jpg[sof + 9]
    sampling = [jpg[sof + 10 + 3 * k + 1] for k in range(n_components)]
    assert n_components == 3 and sampling == [0x11, 0x11, 0x11]
