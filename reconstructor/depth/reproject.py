"""Stereo depth maps drawn into another camera: every valid pixel as a world point with its
footprint (``depth_map_points``), splatted far to near with a z-buffer (``reproject_points``).

Two users: the depth-reprojection baseline (``evaluation/baselines.py``: the maps' colours in a
held-out camera) and the training's depth term (``splats/depth_term.py``: the maps' depth in
each input view, the target that keeps Gaussians on the surfaces stereo saw).

Each pixel of a depth map becomes a square splat whose side is that pixel's footprint at its
depth (depth / focal length: neighbouring pixels of one surface then meet without gaps when seen
from the depth map's own camera, and spread apart, leaving holes, where the target looks at that
surface more closely or from a grazing angle). Splats are drawn far to near so that the nearest
wins (a painter's z-buffer). Pixels no point reaches stay empty (depth inf).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from protocol.camera import Camera, Pose
from reconstructor.data.views import View

if TYPE_CHECKING:
    from reconstructor.depth.stereo import DepthMap

# a depth-map pixel drawn into a view of similar resolution covers about one pixel: a splat
# radius of 1 closes the gaps of a resampled grid without smearing edges
TARGET_MAX_RADIUS_PX = 1


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
    # a footprint of one pixel is radius 0; the 1e-3 px keeps float noise (a float32 focal
    # length against a float64 one) from rounding it up to a 3x3 splat
    radius = np.clip(np.ceil(0.5 * size * intr.fx_px / z - 0.5 - 1e-3), 0, max_radius_px)
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


def depth_targets(
    views: Sequence[View],
    sources: Mapping[str, tuple[DepthMap, Pose]],
) -> dict[str, np.ndarray]:
    """Each view's depth target (H, W) float32, NaN where empty or where the view has no image
    content: the depth map of ``sources[view.name]`` (the view's own stereo pair's map and that
    pair's left sensor pose) drawn into the view. Views without a source get none."""
    out: dict[str, np.ndarray] = {}
    drawn: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for view in views:
        source = sources.get(view.name)
        if source is None:
            continue
        if id(source[0]) not in drawn:  # a pair's map serves its left and right views
            points, _colours, sizes = depth_map_points([source])
            drawn[id(source[0])] = (points, sizes)
        points, sizes = drawn[id(source[0])]
        camera = Camera(name=view.name, intrinsics=view.intrinsics, pose=view.pose)
        _, depth = reproject_points(
            points, np.zeros_like(points), camera, point_size_m=sizes,
            max_radius_px=TARGET_MAX_RADIUS_PX,
        )  # fmt: skip
        depth = np.where(np.isfinite(depth), depth, np.nan).astype(np.float32)
        depth[view.mask.numpy() < 0.5] = np.nan
        out[view.name] = depth
    return out
