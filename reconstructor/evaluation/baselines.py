"""The depth-reprojection baseline: every valid pixel of every stereo depth map drawn straight into
a target camera (``reproject_depth_maps``), holes left as holes.

Each pixel of a depth map becomes a square splat whose side is that pixel's footprint at its
depth (depth / focal length: neighbouring pixels of one surface then meet without gaps when seen
from the depth map's own camera, and spread apart, leaving holes, where the target looks at that
surface more closely or from a grazing angle). Splats are drawn far to near so that the nearest
wins (a painter's z-buffer). Pixels no point reaches stay at the background and are counted as
holes. This is what the paper's "depth reprojection" row measures: the geometry and colours of
the depth maps alone, at full resolution, with no fusion, no cap and no optimisation. (Until
issue 22 the row drew the fused cloud after its 200k-point cap, which measured the cap.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from protocol.camera import Camera, Pose

if TYPE_CHECKING:
    from reconstructor.depth.stereo import DepthMap


def reproject_points(
    points_m: np.ndarray,
    colours: np.ndarray,
    camera: Camera,
    *,
    point_size_m: float | np.ndarray,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    max_radius_px: int = 6,
    near_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) float32 in [0, 1], depth_m (H, W) with inf where empty); points nearer
    than ``near_m`` (and 1 mm) are left out. ``point_size_m``: one side length for all points,
    or one per point (N,).

    ``camera`` is treated as a pinhole (its distortion is ignored: render into undistorted views).
    """
    intr = camera.intrinsics
    w, h = intr.width_px, intr.height_px
    image = np.empty((h, w, 3), np.float32)
    image[:] = np.asarray(background, np.float32)
    depth = np.full((h, w), np.inf, np.float32)
    if len(points_m) == 0:
        return image, depth
    pc = camera.pose.transform(np.asarray(points_m, np.float64))
    z = pc[:, 2]
    front = z > max(near_m, 1e-3)
    pc, z, col = pc[front], z[front], np.asarray(colours, np.float32)[front]
    size = np.broadcast_to(np.asarray(point_size_m, np.float64), (len(points_m),))[front]
    u = intr.fx_px * pc[:, 0] / z + intr.cx_px
    v = intr.fy_px * pc[:, 1] / z + intr.cy_px
    radius = np.clip(np.ceil(0.5 * size * intr.fx_px / z - 0.5), 0, max_radius_px)
    inside = (u > -max_radius_px) & (u < w + max_radius_px) & (v > -max_radius_px)
    inside &= v < h + max_radius_px
    order = np.argsort(-z[inside], kind="stable")  # far first, near last: near overwrites
    u, v, z = u[inside][order], v[inside][order], z[inside][order]
    radius, col = radius[inside][order].astype(np.int64), col[inside][order]
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    r_max = int(radius.max()) if len(radius) else 0
    for dy in range(-r_max, r_max + 1):
        for dx in range(-r_max, r_max + 1):
            sel = (np.abs(dx) <= radius) & (np.abs(dy) <= radius)
            x, y = ui[sel] + dx, vi[sel] + dy
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            x, y, zz, cc = x[ok], y[ok], z[sel][ok], col[sel][ok]
            # within one offset, later (nearer) points overwrite earlier ones; across offsets a
            # far point must not overwrite a nearer one already drawn
            nearer = zz < depth[y, x]
            depth[y[nearer], x[nearer]] = zz[nearer]
            image[y[nearer], x[nearer]] = cc[nearer]
    return image, depth


def depth_map_points(
    sources: Sequence[tuple[DepthMap, Pose]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every valid pixel of each (depth map, its left sensor's world-to-camera pose) as world
    points (M, 3), colours (M, 3) in 0..1 and footprints (M,) in metres (depth / focal)."""
    points, colours, sizes = [], [], []
    for depth, pose in sources:
        p, c = depth.points_in_world(pose)
        z = depth.depth_m[np.nonzero(depth.valid)].astype(np.float64)  # the same order as p
        points.append(p)
        colours.append(c)
        sizes.append(z / depth.intrinsics.fx_px)
    if not points:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0)
    return np.concatenate(points), np.concatenate(colours), np.concatenate(sizes)


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
