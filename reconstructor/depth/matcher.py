"""The stereo matcher seam: ``StereoMatcher``, dense disparity for one rectified pair.

The built-in matcher is ``sgbm.SgbmWlsMatcher``; ``matchers.load_matcher`` picks one by name,
including plug-ins (a learned matcher such as FoundationStereo) registered in the entry-point
group ``egosurg.stereo_matchers``.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import numpy as np


class StereoMatcher(abc.ABC):
    """Dense disparity for one rectified pair.

    ``match`` takes the rectified left and right images, (H, W, 3) uint8 RGB of the same size,
    and returns (H, W) float32 disparity in pixels of that size (``x_left - x_right``); NaN or a
    value <= 0 marks a pixel without a trustworthy match. ``min_disparity_px`` and
    ``max_disparity_px`` bound the disparities of the scene's depth range: a matcher may use them
    to limit its search, and may ignore them.
    """

    name: ClassVar[str] = "matcher"
    needs_weights: ClassVar[bool] = True  # a learned matcher cannot run without its weights

    @abc.abstractmethod
    def match(
        self,
        left_rgb: np.ndarray,
        right_rgb: np.ndarray,
        *,
        min_disparity_px: float,
        max_disparity_px: float,
    ) -> np.ndarray: ...
