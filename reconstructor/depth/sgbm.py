"""The built-in stereo matcher: OpenCV SGBM with a right-view matcher and a WLS filter (CPU only,
no weights), with the checks that decide which of its disparities to keep."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from reconstructor.depth.matcher import StereoMatcher
from reconstructor.depth.stereo_config import StereoConfig
from reconstructor.depth.stereo_occlusion import fill_left_border


class SgbmWlsMatcher(StereoMatcher):
    """OpenCV SGBM (3-way) with a right-view matcher and a WLS filter; CPU only, no weights.

    A pixel keeps its WLS-filtered disparity only where all of these hold (measured on the sim,
    each removes a kind of error the others miss):
    - left-right check: the raw left disparity and the raw right one at the matched pixel agree
      within ``lr_max_diff_px`` (occlusions, mismatches);
    - photometric check: high-passed ``zncc_window_px``-square patches at the match correlate
      (ZNCC) at least ``min_zncc``. On a blank wall only sensor noise is left after the
      high-pass, and noise does not correlate between two sensors; SGBM's smoothness term
      otherwise paints such walls at a consistent but wrong depth that passes the left-right
      check;
    - WLS agreement: the filtered disparity is within ``wls_max_change_px`` of the raw one
      (the halo SGBM's blocks fatten around foreground edges, and WLS's over-smoothed slopes).
      With ``keep_sgbm_within_px`` above it, a pixel whose two estimates differ by more than
      that but at most ``keep_sgbm_within_px`` keeps SGBM's own disparity instead (where WLS
      over-smooths a slope, SGBM's is the better of the two: on real pairs 9-14 % of those
      answers are > 2 px off against WLS's 17-28 %).

    With ``keep_smooth_sgbm_within_px`` SGBM's own answers further, up to that disagreement,
    where its disparity is smooth around the pixel (within ``SMOOTH_RANGE_PX`` over
    ``SMOOTH_WINDOW_PX`` square).

    With ``fill_left_border``, the left border's band that has no partner in the right image is
    then filled from each row's first answer where its width fits (``stereo_occlusion.py``).
    """

    name = "sgbm"
    needs_weights = False

    def __init__(self, config: StereoConfig | None = None) -> None:
        self.config = StereoConfig() if config is None else config

    def match(
        self,
        left_rgb: np.ndarray,
        right_rgb: np.ndarray,
        *,
        min_disparity_px: float,
        max_disparity_px: float,
    ) -> np.ndarray:
        raw = self.raw_disparities(
            left_rgb,
            right_rgb,
            min_disparity_px=min_disparity_px,
            max_disparity_px=max_disparity_px,
        )
        out = self.estimate(raw)
        out[~self.keep(left_rgb, right_rgb, raw)] = np.nan
        if self.config.fill_left_border:
            out = fill_left_border(out, self.config.left_border_slack_px)
        return out

    def estimate(self, raw: RawDisparities) -> np.ndarray:
        """(H, W) float32: each pixel's answer if it is kept, the WLS map, or SGBM's own
        disparity where they differ by more than ``wls_max_change_px`` and
        ``keep_sgbm_within_px`` is on (the class docstring)."""
        cfg = self.config
        if max(cfg.keep_sgbm_within_px, cfg.keep_smooth_sgbm_within_px) <= cfg.wls_max_change_px:
            return raw.filtered.copy()
        with np.errstate(invalid="ignore"):
            differs = np.abs(raw.filtered - raw.left) > cfg.wls_max_change_px
        return np.where(differs, raw.left, raw.filtered).astype(np.float32)

    def raw_disparities(
        self,
        left_rgb: np.ndarray,
        right_rgb: np.ndarray,
        *,
        min_disparity_px: float,
        max_disparity_px: float,
    ) -> RawDisparities:
        """SGBM's left and right-view disparities and the WLS-filtered map, before any check
        (apart so that the checks can be tuned on one matching: ``bench/bench_stereo.py``)."""
        cfg = self.config
        w = cfg.block_size_px
        channels = left_rgb.shape[2] if left_rgb.ndim == 3 else 1
        min_d = max(0, math.floor(min_disparity_px) - 1)
        num_d = 16 * math.ceil((math.ceil(max_disparity_px) + 1 - min_d) / 16)
        left_matcher = cv2.StereoSGBM.create(
            minDisparity=min_d,
            numDisparities=num_d,
            blockSize=w,
            P1=8 * channels * w * w,
            P2=32 * channels * w * w,
            disp12MaxDiff=-1,  # the explicit left-right check below replaces SGBM's own
            uniquenessRatio=cfg.uniqueness_ratio,
            speckleWindowSize=cfg.speckle_window_px,
            speckleRange=cfg.speckle_range_px,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
        right_matcher = cv2.ximgproc.createRightMatcher(left_matcher)
        # SGBM leaves the first min_d + num_d columns of the left view unmatched, and the right
        # view's matcher (which searches rightwards) the last ones. Black padding on both sides
        # lets each match every pixel whose partner is inside the other image; padding only on
        # the left emptied the right-most ~max_disparity columns through the left-right check.
        pad = min_d + num_d
        lp = cv2.copyMakeBorder(left_rgb, 0, 0, pad, pad, cv2.BORDER_CONSTANT, value=0)
        rp = cv2.copyMakeBorder(right_rgb, 0, 0, pad, pad, cv2.BORDER_CONSTANT, value=0)
        disp_left = left_matcher.compute(lp, rp)
        disp_right = right_matcher.compute(rp, lp)
        wls = cv2.ximgproc.createDisparityWLSFilter(left_matcher)
        wls.setLambda(cfg.wls_lambda)
        wls.setSigmaColor(cfg.wls_sigma_color)
        crop = slice(pad, pad + left_rgb.shape[1])
        filtered = wls.filter(disp_left, lp, disparity_map_right=disp_right)[:, crop]
        return RawDisparities(
            left=sgbm_disparity(disp_left[:, crop], min_d, num_d),
            right=sgbm_disparity(disp_right[:, crop], min_d, num_d, right_view=True),
            filtered=filtered.astype(np.float32) / 16.0,
        )

    def keep(self, left_rgb: np.ndarray, right_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        """(H, W) bool: the pixels whose filtered disparity passes every check of the class
        docstring (a check whose threshold disables it is skipped)."""
        cfg = self.config
        ok = lr_consistent(raw.left, raw.right, cfg.lr_max_diff_px)
        within = max(cfg.wls_max_change_px, cfg.keep_sgbm_within_px)
        with np.errstate(invalid="ignore"):
            change = np.abs(raw.filtered - raw.left)
            agree = change <= within
            if cfg.keep_smooth_sgbm_within_px > within:
                smooth = disparity_range(raw.left, SMOOTH_WINDOW_PX) <= SMOOTH_RANGE_PX
                agree |= (change <= cfg.keep_smooth_sgbm_within_px) & smooth
        ok &= agree
        if cfg.min_zncc > -1.0:
            # The window's pixels that failed a check are warped by 0, or by their best
            # estimate (SGBM's, else WLS's) with ``zncc_warp_failed_by_best``: see its comment.
            if cfg.zncc_warp_failed_by_best:
                warp = np.where(np.isfinite(raw.left), raw.left, raw.filtered)
            else:
                warp = np.where(ok, raw.left, 0.0)
            zncc = zncc_at_disparity(_grey(left_rgb), _grey(right_rgb), warp, cfg.zncc_window_px)
            ok &= zncc >= cfg.min_zncc
        return ok


@dataclass(frozen=True, eq=False)
class RawDisparities:
    """One SGBM matching, (H, W) float32 px each: ``left`` and ``right`` are the raw positive
    disparities of each view (NaN where SGBM had none), ``filtered`` the WLS map."""

    left: np.ndarray
    right: np.ndarray
    filtered: np.ndarray


HIGHPASS_SIGMA_PX = 3.0  # removes shading gradients, which correlate at any disparity
# keep_smooth_sgbm_within_px: SGBM's own disparity counts as smooth where it varies by at most
# this over the window around the pixel
SMOOTH_WINDOW_PX = 5
SMOOTH_RANGE_PX = 1.0


def sgbm_disparity(
    fixed_point: np.ndarray, min_d: int, num_d: int, *, right_view: bool = False
) -> np.ndarray:
    """(H, W) float32 positive disparities in px from OpenCV's int16 1/16-px output, NaN where
    OpenCV wrote its invalid code or anything outside the searched range.

    The left matcher searches ``[min_d, min_d + num_d)``; the right-view matcher (from
    ``createRightMatcher``) searches the negated range ``[-(min_d + num_d) + 1, -min_d]``.
    OpenCV's invalid code is ``(minDisparity - 1) * 16``, which for the right view negates to
    ``min_d + num_d``: a plausible-looking disparity unless it is masked here.
    """
    disp = fixed_point.astype(np.float32) / (-16.0 if right_view else 16.0)
    searched = (disp >= min_d) & (disp <= min_d + num_d - 1)
    return np.where(searched, disp, np.float32(np.nan)).astype(np.float32)


def lr_consistent(disp_left: np.ndarray, disp_right: np.ndarray, max_diff_px: float) -> np.ndarray:
    """(H, W) bool: the left disparity ``d`` at ``x`` and the right one at ``x - d`` agree.

    Both maps are positive disparities (``x_left - x_right``), each in its own image.
    """
    w = disp_left.shape[1]
    xs = np.arange(w, dtype=np.float32)[None, :]
    with np.errstate(invalid="ignore"):
        x_r = np.rint(xs - disp_left)
        inside = np.isfinite(disp_left) & (disp_left > 0) & (x_r >= 0) & (x_r <= w - 1)
    x_ri = np.where(inside, x_r, 0).astype(np.intp)
    d_r = np.take_along_axis(disp_right, x_ri, axis=1)
    return inside & (d_r > 0) & (np.abs(disp_left - d_r) <= max_diff_px)


def disparity_range(disp_px: np.ndarray, window_px: int) -> np.ndarray:
    """(H, W) float32: the largest minus the smallest finite disparity in the ``window_px``
    square around each pixel (NaN where the window has none)."""
    finite = np.isfinite(disp_px)
    k = np.ones((window_px, window_px), np.uint8)
    top = cv2.dilate(np.where(finite, disp_px, -np.inf).astype(np.float32), k)
    low = cv2.erode(np.where(finite, disp_px, np.inf).astype(np.float32), k)
    seen = cv2.dilate(finite.astype(np.uint8), k) > 0
    with np.errstate(invalid="ignore", over="ignore"):
        return np.where(seen, top - low, np.nan).astype(np.float32)


def zncc_at_disparity(
    left_grey: np.ndarray, right_grey: np.ndarray, disp_px: np.ndarray, window_px: int
) -> np.ndarray:
    """(H, W) float32 zero-mean normalised cross-correlation of ``window_px`` square patches of
    the high-passed left image and the right image sampled at ``x - disp_px`` (bilinear)."""
    h, w = left_grey.shape
    map_x = np.arange(w, dtype=np.float32)[None, :] - disp_px.astype(np.float32)
    map_y = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    a = _highpass(left_grey)
    b = _highpass(
        cv2.remap(
            right_grey,
            map_x,
            np.ascontiguousarray(map_y),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    )
    k = (window_px, window_px)
    ma, mb = cv2.blur(a, k), cv2.blur(b, k)
    var_a = cv2.blur(a * a, k) - ma * ma
    var_b = cv2.blur(b * b, k) - mb * mb
    cov = cv2.blur(a * b, k) - ma * mb
    return cov / np.sqrt(np.maximum(var_a * var_b, 1e-6))


def _grey(rgb: np.ndarray) -> np.ndarray:
    if rgb.ndim == 2:
        return rgb.astype(np.float32)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)


def _highpass(img: np.ndarray) -> np.ndarray:
    return img - cv2.GaussianBlur(img, (0, 0), HIGHPASS_SIGMA_PX)
