"""The depth-reprojection baseline: every valid pixel of every stereo depth map drawn straight into
a target camera (``reproject_depth_maps``), holes left as holes.

Each pixel of a depth map becomes a square splat of its footprint, drawn far to near
(``reconstructor/depth/reproject.py``, shared with the training's depth term). Pixels no point
reaches stay at the background and are counted as holes. This is what the paper's "depth
reprojection" row measures: the geometry and colours of the depth maps alone, at full
resolution, with no fusion, no cap and no optimisation. (Before the retune the row drew the fused
cloud after its 200k-point cap, which measured the cap.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from protocol.camera import Camera, Pose
from reconstructor.depth.reproject import depth_map_points, reproject_points

if TYPE_CHECKING:
    from reconstructor.depth.stereo import DepthMap


def reproject_depth_maps(
    sources: Sequence[tuple[DepthMap, Pose]],
    camera: Camera,
    *,
    near_m: float = 0.0,
    max_radius_px: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) float32 over black, holes (H, W) bool): the depth maps' pixels drawn
    into ``camera`` (a pinhole); holes are the pixels no depth-map pixel reaches."""
    points, colours, sizes = depth_map_points(sources)
    image, depth = reproject_points(
        points, colours, camera, point_size_m=sizes, near_m=near_m, max_radius_px=max_radius_px
    )
    return image, ~np.isfinite(depth)


def hole_fraction(holes: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The share of the compared pixels (``mask``; all when None) that are holes."""
    if mask is None:
        return float(holes.mean())
    return float(holes[mask].mean()) if mask.any() else 0.0
