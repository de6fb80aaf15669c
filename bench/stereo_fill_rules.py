"""Rules tried for keeping the densest config's extra answers only where they are precise (bench
rows of ``bench/bench_stereo_real.py``; EVALUATION.md, "Why the densest config loses egocentric
PSNR"). Each is ``bench/configs/stereo_densest.toml``'s matcher with one rule on the answers its
options add to the default's checks (the *extras*: kept by this config's checks, not by the
default's); the left border's band is filled afterwards as before.

- ``RelativeAgreement``: SGBM's own disparity is kept only where it and the WLS map differ by
  at most ``rel`` of the disparity (the depth error the disagreement allows), not by an absolute
  1.5-2.5 px: a 1 px disagreement is 1 % of the depth at Aloe's 100 px and 6 % at the sim's 16.
- ``TextureGate``: an extra is kept only where the left image's high-passed patch (the
  photometric check's window) varies by at least ``min_std`` grey levels.
- ``SmoothGuard``: an extra is kept only where SGBM's disparity is smooth around it (within 1 px
  over 5 x 5, the test ``keep_smooth_sgbm_within_px`` uses), so never across a depth jump such
  as a person's silhouette.
"""

from __future__ import annotations

import abc
from dataclasses import replace

import cv2
import numpy as np

from reconstructor.depth.sgbm import (
    SMOOTH_RANGE_PX,
    SMOOTH_WINDOW_PX,
    RawDisparities,
    SgbmWlsMatcher,
    _grey,
    _highpass,
    disparity_range,
)
from reconstructor.depth.stereo_config import StereoConfig


def densest() -> StereoConfig:
    """``bench/configs/stereo_densest.toml``'s ``[stereo]`` table."""
    return StereoConfig(
        zncc_warp_failed_by_best=True,
        keep_sgbm_within_px=1.5,
        keep_smooth_sgbm_within_px=2.5,
        fill_left_border=True,
    )


class _ExtrasRule(SgbmWlsMatcher):
    """The config's checks, with the extras (kept here, not by the default's checks) passed
    through ``allow``."""

    def keep(self, left_rgb: np.ndarray, right_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        ok = super().keep(left_rgb, right_rgb, raw)
        default = replace(
            self.config,
            zncc_warp_failed_by_best=False,
            keep_sgbm_within_px=0.0,
            keep_smooth_sgbm_within_px=0.0,
        )
        base = SgbmWlsMatcher(default).keep(left_rgb, right_rgb, raw)
        extras = ok & ~base
        return base | (extras & self.allow(left_rgb, raw))

    @abc.abstractmethod
    def allow(self, left_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        """(H, W) bool: where an extra may stay."""


class RelativeAgreement(_ExtrasRule):
    def __init__(self, config: StereoConfig | None = None, rel: float = 0.03) -> None:
        super().__init__(config)
        self.rel = rel

    def allow(self, left_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            change = np.abs(raw.filtered - raw.left)
            return (change <= self.config.wls_max_change_px) | (change <= self.rel * raw.left)


class TextureGate(_ExtrasRule):
    def __init__(self, config: StereoConfig | None = None, min_std: float = 2.0) -> None:
        super().__init__(config)
        self.min_std = min_std

    def allow(self, left_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        a = _highpass(_grey(left_rgb))
        k = (self.config.zncc_window_px, self.config.zncc_window_px)
        mean = cv2.blur(a, k)
        var = cv2.blur(a * a, k) - mean * mean
        return var >= self.min_std**2


class SmoothGuard(_ExtrasRule):
    def allow(self, left_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return disparity_range(raw.left, SMOOTH_WINDOW_PX) <= SMOOTH_RANGE_PX
