"""Filling the holes stereo leaves on blank surfaces, so that every surface gets Gaussians.

Block matching cannot match a blank wall or ceiling (the sim's paint, and real ones), and the
stereo stage rightly leaves them without depth. But the splats are never densified (the paper's
schedule), so a surface without initial points stays a hole in every render. This stage
spreads the confident disparity into the holes with an edge-aware smoother guided by the
image (normalised convolution with OpenCV's fast global smoother): inside a blank wall the
disparity of its textured rims (corners, doors, fittings) spreads across, and colour edges stop
it. A filled pixel is kept when enough confident disparity reached it (``min_weight``) and its
depth is in range. Filled points are marked so callers can give them less trust.

Disparity, not depth, is smoothed: a plane's disparity is linear in the image, its depth is not.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from protocol.camera import Pose
from reconstructor.errors import ReconstructConfigError
from reconstructor.stereo import DepthMap


@dataclass(frozen=True, kw_only=True)
class FillConfig:
    enabled: bool = True
    smoothness: float = 2000.0  # the smoother's lambda: how far disparity spreads
    sigma_color: float = 6.0  # colour difference (0..255) that stops it
    min_weight: float = 0.05  # share of confident disparity that must reach a filled pixel
    stride_px: int = 2  # keep every n-th filled pixel in each direction: blank walls need few

    def __post_init__(self) -> None:
        if self.smoothness <= 0 or self.sigma_color <= 0:
            raise ReconstructConfigError(
                f"fill: smoothness and sigma_color must be positive, got {self.smoothness}, "
                f"{self.sigma_color}"
            )
        if not 0 < self.min_weight < 1:
            raise ReconstructConfigError(f"fill.min_weight={self.min_weight}: must be in (0, 1)")
        if self.stride_px < 1:
            raise ReconstructConfigError(f"fill.stride_px={self.stride_px}: must be >= 1")


def fill_disparity(depth: DepthMap, config: FillConfig) -> tuple[np.ndarray, np.ndarray]:
    """(filled disparity (H, W) float32, mask of the pixels filled here (H, W) bool)."""
    fb = depth.intrinsics.fx_px * depth.baseline_m
    valid = depth.valid & np.isfinite(depth.depth_m)
    disp = np.where(valid, fb / np.where(valid, depth.depth_m, 1.0), 0.0).astype(np.float32)
    weight = valid.astype(np.float32)
    guide = depth.rgb

    def smooth(x: np.ndarray) -> np.ndarray:
        return cv2.ximgproc.fastGlobalSmootherFilter(
            guide, x, config.smoothness, config.sigma_color
        )

    num, den = smooth(disp * weight), smooth(weight)
    with np.errstate(invalid="ignore", divide="ignore"):
        filled = np.where(den > config.min_weight, num / den, np.nan).astype(np.float32)
    mask = ~valid & np.isfinite(filled) & (filled > 0)
    sub = np.zeros_like(mask)
    sub[:: config.stride_px, :: config.stride_px] = True
    return filled, mask & sub


def fill_points_in_world(
    depth: DepthMap,
    left_pose: Pose,
    config: FillConfig,
    *,
    min_depth_m: float,
    max_depth_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of the filled pixels (none when disabled)."""
    if not config.enabled:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    filled, mask = fill_disparity(depth, config)
    fb = depth.intrinsics.fx_px * depth.baseline_m
    v, u = np.nonzero(mask)
    z = fb / filled[v, u].astype(np.float64)
    keep = (z >= min_depth_m) & (z <= max_depth_m)
    v, u, z = v[keep], u[keep], z[keep]
    k = depth.intrinsics
    rect = np.stack([(u - k.cx_px) / k.fx_px * z, (v - k.cy_px) / k.fy_px * z, z], axis=1)
    cam = rect @ depth.rect_from_left
    world = (cam - left_pose.t_m) @ left_pose.R
    colours = depth.rgb[v, u].astype(np.float32) / 255.0
    return world.astype(np.float32), colours
