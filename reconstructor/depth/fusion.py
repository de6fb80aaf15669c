"""Fuse the stereo point clouds of one timestamp into one cleaned cloud.

As in the paper: merge every camera's world points, voxel-downsample (one point per
``voxel_m`` cube, at the mean position and colour of the points in it), then drop statistical
outliers (points whose mean distance to their ``outlier_nb_neighbors`` nearest neighbours is
more than ``outlier_std_ratio`` standard deviations above the cloud's average).

Downsampling first evens out the density between near and far cameras. If more than
``max_points`` voxels remain, a seeded uniform subsample is taken *before* the outlier search:
that search is the slowest step (a sim frame's 680k voxels take several times longer than a
200k subsample), and its test is relative to the cloud's own spacing, so a uniform subsample
keeps isolated points isolated.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from reconstructor.errors import FusionError, ReconstructConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class FusionConfig:
    voxel_m: float = 0.01
    outlier_nb_neighbors: int = 20
    outlier_std_ratio: float = 2.0
    # the rasterizer's reference load (the design's budget: 200k Gaussians at 960x600 on 2 cores)
    max_points: int = 200_000
    seed: int = 0  # which points survive the cap, reproducibly

    def __post_init__(self) -> None:
        if not 0 < self.voxel_m <= 1.0:
            raise ReconstructConfigError(
                f"FusionConfig.voxel_m={self.voxel_m!r}: must be in (0, 1] metres"
            )
        if self.outlier_nb_neighbors < 1:
            raise ReconstructConfigError(
                f"FusionConfig.outlier_nb_neighbors={self.outlier_nb_neighbors!r}: must be >= 1"
            )
        if self.outlier_std_ratio <= 0:
            raise ReconstructConfigError(
                f"FusionConfig.outlier_std_ratio={self.outlier_std_ratio!r}: must be positive"
            )
        if self.max_points < 1:
            raise ReconstructConfigError(
                f"FusionConfig.max_points={self.max_points!r}: must be at least 1"
            )


@dataclass(frozen=True, eq=False)
class FusedCloud:
    """``points_m`` (N, 3) float32 world metres, ``colours`` (N, 3) float32 in 0..1, and the
    point count after each step (``input_points``, ``after_voxel``, ``after_cap``,
    ``after_outlier`` = N)."""

    points_m: np.ndarray
    colours: np.ndarray
    stats: dict[str, int] = field(default_factory=dict)

    @property
    def num(self) -> int:
        return len(self.points_m)

    @functools.cached_property
    def spacing_m(self) -> float:
        """The median nearest-neighbour distance of the points."""
        return point_spacing_m(self.points_m)


def point_spacing_m(points_m: np.ndarray, *, sample: int = 20_000, seed: int = 0) -> float:
    """The median distance from a point to its nearest neighbour (on a seeded subsample of the
    query points; the tree holds them all)."""
    pts = np.asarray(points_m, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    rng = np.random.default_rng(seed)
    query = pts if len(pts) <= sample else pts[rng.choice(len(pts), sample, replace=False)]
    # sliding-midpoint splits: the median build can recurse without end on points sharing a
    # coordinate (scipy#5564; see gaussians.nearest_neighbour_scale)
    dist, _ = cKDTree(pts, balanced_tree=False).query(query, k=2)
    return float(np.median(dist[:, 1]))


def fuse(
    clouds: Sequence[tuple[np.ndarray, np.ndarray]], config: FusionConfig | None = None
) -> FusedCloud:
    """Merge ``(points_world (M, 3), colours (M, 3) in 0..1)`` clouds into one cleaned cloud."""
    cfg = config or FusionConfig()
    points, colours = _concatenate(clouds)
    stats = {"input_points": len(points)}
    import open3d as o3d  # here, not at import: 4 s, and the config and the GPU machine need none

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(points.astype(np.float64))
    pcd.colors = o3d.utility.Vector3dVector(colours.astype(np.float64))
    pcd = pcd.voxel_down_sample(cfg.voxel_m)
    stats["after_voxel"] = len(pcd.points)
    if len(pcd.points) > cfg.max_points:
        keep = np.random.default_rng(cfg.seed).choice(len(pcd.points), cfg.max_points, False)
        pcd = pcd.select_by_index(np.sort(keep).tolist())
    stats["after_cap"] = len(pcd.points)
    if len(pcd.points) > cfg.outlier_nb_neighbors:
        pcd, _ = pcd.remove_statistical_outlier(
            nb_neighbors=cfg.outlier_nb_neighbors, std_ratio=cfg.outlier_std_ratio
        )
    else:
        log.warning(
            "only %d points after voxel downsampling: too few for outlier removal (needs > %d)",
            len(pcd.points),
            cfg.outlier_nb_neighbors,
        )
    stats["after_outlier"] = len(pcd.points)
    out_points = np.asarray(pcd.points, dtype=np.float32)
    out_colours = np.asarray(pcd.colors, dtype=np.float32)
    if not len(out_points):
        raise FusionError(
            f"no points left after fusion (stats {stats}); the depth maps are empty or all "
            "outliers: check the calibration and that the images show the room"
        )
    log.info("fused %s", ", ".join(f"{k} {v}" for k, v in stats.items()))
    return FusedCloud(out_points, out_colours, stats)


def _concatenate(
    clouds: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    if not len(clouds):
        raise FusionError("no point clouds to fuse: give at least one (points, colours) pair")
    pts, cols = [], []
    for i, (p, c) in enumerate(clouds):
        p, c = np.asarray(p), np.asarray(c)
        if p.ndim != 2 or p.shape[1] != 3 or c.shape != p.shape:
            raise FusionError(
                f"cloud {i}: points {p.shape} and colours {c.shape} must both be (M, 3)"
            )
        if not np.isfinite(p).all():
            raise FusionError(
                f"cloud {i}: {int((~np.isfinite(p)).any(axis=1).sum())} points "
                "are not finite; drop invalid depth pixels before fusing"
            )
        if len(c) and (c.min() < 0.0 or c.max() > 1.0):
            raise FusionError(
                f"cloud {i}: colours span {c.min():g}..{c.max():g}; they must be in 0..1 "
                "(divide 8-bit colours by 255)"
            )
        pts.append(p)
        cols.append(c)
    points = np.concatenate(pts)
    if not len(points):
        raise FusionError(
            f"all {len(clouds)} point clouds are empty: no valid depth in any camera; check "
            "that the images are exposed and the stereo calibration matches the cameras"
        )
    return points, np.concatenate(cols)
