"""Real rectified stereo pairs with ground-truth disparity, each installed by a package name.

- ``motorcycle``: Middlebury 2014 Motorcycle as scikit-image ships it inside its wheel
  (``skimage.data.stereo_motorcycle``, 741 x 500, disparity with ``inf`` where unknown). Installed
  by the project's ``bench`` extra (``pip install -e '.[bench]'``; ``make`` installs it). The
  images and truth are the 2964 x 2000 originals ("perfect" rectification) area-averaged by 4,
  so the disparity is a quarter of Middlebury's (7.2-59.9 px; ndisp 270 / 4) and is the left
  view's (``x_right = x_left - d``, despite the docstring's ``img_left[10, 10 + disp]``
  example): warped by it the right view matches the left best at a shift of 0, not +-0.25 px
  (``tests/reconstructor/test_stereo_real.py`` checks +-1 px). ``doffs`` (31.1 px at this size)
  only matters for depth, not for disparity.
- ``aloe``: Middlebury 2006 Aloe at full size (1282 x 1110) from OpenCV's samples in Debian's
  ``opencv-doc`` (``aloeL.jpg``, ``aloeR.jpg``, ``aloeGT.png``: integer disparity of the left view,
  0 where unknown). Installed by ``make system-deps`` as root (``apt-get install opencv-doc``).
- ``aloe-half``: the same at half size (area-averaged images, disparity halved), the size at
  which the pipeline matches an HD1200 pair (``StereoConfig.for_resolution``).

Nothing is fetched at run time: a pair whose package is missing raises ``PairMissingError`` with
the command that installs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

OPENCV_DOC_DATA = Path("/usr/share/doc/opencv-doc/examples/data")
PAIR_NAMES = ("motorcycle", "aloe", "aloe-half")


class PairMissingError(FileNotFoundError):
    """A pair's package is not installed; the message says how to install it."""


@dataclass(frozen=True, kw_only=True, eq=False)
class RealPair:
    """One rectified pair: (H, W, 3) uint8 RGB images and the left view's true disparity,
    (H, W) float32 px (``x_left - x_right``), NaN where the truth is unknown."""

    name: str
    left_rgb: np.ndarray
    right_rgb: np.ndarray
    disparity_px: np.ndarray
    source: str


def load_pair(name: str) -> RealPair:
    """The pair called ``name`` (one of ``PAIR_NAMES``)."""
    if name == "motorcycle":
        return _motorcycle()
    if name == "aloe":
        return _aloe()
    if name == "aloe-half":
        return _half(_aloe(), "aloe-half")
    raise ValueError(f"no stereo pair called {name!r}; choose from {', '.join(PAIR_NAMES)}")


def _motorcycle() -> RealPair:
    try:
        from skimage import data
    except ImportError as e:
        raise PairMissingError(
            "the motorcycle pair ships with scikit-image, which is not installed: "
            "pip install -e '.[bench]'"
        ) from e
    left, right, disp = data.stereo_motorcycle()
    disp = np.where(np.isfinite(disp) & (disp > 0), disp, np.nan).astype(np.float32)
    return RealPair(
        name="motorcycle",
        left_rgb=np.ascontiguousarray(left),
        right_rgb=np.ascontiguousarray(right),
        disparity_px=disp,
        source="Middlebury 2014 Motorcycle (scikit-image)",
    )


def _aloe() -> RealPair:
    paths = [OPENCV_DOC_DATA / f for f in ("aloeL.jpg", "aloeR.jpg", "aloeGT.png")]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise PairMissingError(
            f"the aloe pair comes with Debian's opencv-doc and {missing[0]} is missing: "
            "sudo apt-get install opencv-doc (or make system-deps as root)"
        )
    left, right = (np.ascontiguousarray(_read(p, cv2.IMREAD_COLOR)[:, :, ::-1]) for p in paths[:2])
    gt = _read(paths[2], cv2.IMREAD_GRAYSCALE).astype(np.float32)
    gt[gt == 0] = np.nan
    return RealPair(
        name="aloe",
        left_rgb=left,
        right_rgb=right,
        disparity_px=gt,
        source="Middlebury 2006 Aloe, full size (Debian opencv-doc)",
    )


def _read(path: Path, flags: int) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise PairMissingError(f"{path} is not a readable image: reinstall opencv-doc")
    return img


def _half(pair: RealPair, name: str) -> RealPair:
    h, w = pair.disparity_px.shape
    size = (w // 2, h // 2)

    def shrink(img: np.ndarray) -> np.ndarray:
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)

    # nearest, not averaged: a mean across a depth edge is a disparity no surface has
    disp = cv2.resize(pair.disparity_px, size, interpolation=cv2.INTER_NEAREST) / 2.0
    return RealPair(
        name=name,
        left_rgb=shrink(pair.left_rgb),
        right_rgb=shrink(pair.right_rgb),
        disparity_px=disp.astype(np.float32),
        source=pair.source.replace("full size", "half size"),
    )
