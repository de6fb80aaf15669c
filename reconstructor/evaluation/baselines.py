"""The depth-reprojection baseline: the fused stereo points drawn straight into a target camera.

Each point is a square splat whose side matches the cloud's point spacing at its depth (at
least one pixel; ``point_spacing_m``: after the fusion's cap the cloud is sparser than its
voxels, and drawing voxel-sized squares would leave most pixels empty), drawn far to near so
that the nearest point wins (a painter's z-buffer).
Pixels no point reaches stay at the background. This is what the paper's "depth reprojection"
row measures: the geometry and colours of the depth maps alone, with no optimisation.
"""

from __future__ import annotations

import numpy as np

from protocol.camera import Camera


def reproject_points(
    points_m: np.ndarray,
    colours: np.ndarray,
    camera: Camera,
    *,
    point_size_m: float,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    max_radius_px: int = 6,
    near_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) float32 in [0, 1], depth_m (H, W) with inf where empty); points nearer
    than ``near_m`` (and 1 mm) are left out.

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
    u = intr.fx_px * pc[:, 0] / z + intr.cx_px
    v = intr.fy_px * pc[:, 1] / z + intr.cy_px
    radius = np.clip(np.ceil(0.5 * point_size_m * intr.fx_px / z - 0.5), 0, max_radius_px)
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
