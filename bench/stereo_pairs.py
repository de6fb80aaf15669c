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

``at_rig_scale`` shrinks any of them until its median true disparity is the rig's
(``RIG_MEDIAN_DISPARITY_PX``): the rig matches 960 px wide images whose answers lie at a median
16 px (``bench/bench_stereo_extras.py``), the pairs' at 29-59 px, and the matcher's checks are
in pixels, so only at the rig's disparities do they act on a pair as they act on the rig.

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
# the median disparity of the rig's answers on the sim (960 px wide images; EVALUATION.md, "Why
# the densest config loses egocentric PSNR": 15.6 px the default's, 15.9 px the densest's extras)
RIG_MEDIAN_DISPARITY_PX = 16.0


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


def downscaled(pair: RealPair, factor: float, name: str | None = None) -> RealPair:
    """``pair`` shrunk by ``factor`` (< 1) in each direction: the images area-averaged, the
    truth the full-size truth at each new pixel's centre, times the new width over the old
    (disparity is horizontal), NaN where that is NaN. Not averaged: a mean across a depth edge
    is a disparity no surface has, and one across a hole would invent a truth."""
    h, w = pair.disparity_px.shape
    if not 0.0 < factor < 1.0:
        raise ValueError(f"a downscale factor must lie in (0, 1), not {factor}")
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    sx, sy = size[0] / w, size[1] / h  # the factors the rounded size gives

    def centres(n: int, s: float, limit: int) -> np.ndarray:
        # the full-size pixel under each new pixel's centre ((j + 0.5) / s - 0.5 in full-size px)
        return np.clip(np.rint((np.arange(n) + 0.5) / s - 0.5), 0, limit - 1).astype(np.intp)

    rows, cols = centres(size[1], sy, h), centres(size[0], sx, w)
    disp = pair.disparity_px[np.ix_(rows, cols)] * np.float32(sx)

    def shrink(img: np.ndarray) -> np.ndarray:
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)

    return RealPair(
        name=name or f"{pair.name} x{sx:.2f}",
        left_rgb=shrink(pair.left_rgb),
        right_rgb=shrink(pair.right_rgb),
        disparity_px=disp.astype(np.float32),
        source=f"{pair.source}, downscaled x{sx:.3f}",
    )


def at_rig_scale(pair: RealPair, median_px: float = RIG_MEDIAN_DISPARITY_PX) -> RealPair:
    """``pair`` downscaled so that its median true disparity is about ``median_px`` (the rig's);
    named ``<name>@rig``. A pair already at or below it is refused (it would need upscaling)."""
    median = float(np.nanmedian(pair.disparity_px))
    if median <= median_px:
        raise ValueError(
            f"{pair.name}'s median true disparity is {median:.1f} px, not above {median_px} px: "
            "it is already at the rig's scale; judge it as it is"
        )
    return downscaled(pair, median_px / median, name=f"{pair.name}@rig")
