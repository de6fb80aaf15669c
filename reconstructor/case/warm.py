"""Warm start: timestamp t+1 begins from t's trained Gaussians instead of from scratch.

What did not move is kept as trained. What t+1's stereo depth shows to be gone is dropped: a
Gaussian whose centre lies clearly in front of the surface a stereo camera now sees (free space
at t+1: a person walked away, the C-arm swung) cannot be there any more. Where t+1's fused
points lie far from every kept Gaussian (someone arrived), new Gaussians are seeded from those
points as a cold run seeds them. Then training runs far fewer steps (``WarmStartConfig.steps``),
as Dynamic 3D Gaussians (Luiten et al.) and 3DGStream do for later frames.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from scipy.spatial import cKDTree

from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import Timestamp
from reconstructor.depth.stereo import DepthMap
from reconstructor.errors import ReconstructConfigError
from reconstructor.splats.gaussians import GaussianInitConfig, Gaussians, init_from_points

if TYPE_CHECKING:  # fusion imports open3d; the warm-start settings alone must not need it
    from reconstructor.depth.fusion import FusedCloud

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class WarmStartConfig:
    steps: int = 250  # training steps of a warm timestamp (3DGStream: 250 per frame)
    keyframe_every: int = 10  # every this many timestamps one is trained cold
    # a Gaussian this far in front of the observed surface (or this share of its depth, if
    # more) is in free space: stereo noise at 3-4 m is a few centimetres
    free_space_margin_m: float = 0.05
    free_space_margin_ratio: float = 0.03
    # a new point farther than this from every kept Gaussian is new content
    new_point_distance_m: float = 0.03

    def __post_init__(self) -> None:
        if self.steps < 1 or self.keyframe_every < 1:
            raise ReconstructConfigError(
                f"warm start: steps={self.steps} and keyframe_every={self.keyframe_every} must "
                "both be at least 1"
            )
        if min(self.free_space_margin_m, self.new_point_distance_m) <= 0:
            raise ReconstructConfigError("warm start: the distances must be positive metres")

    def describe(self) -> str:
        return (
            f"warm steps={self.steps} keyframe_every={self.keyframe_every} "
            f"margin={self.free_space_margin_m}/{self.free_space_margin_ratio} "
            f"new={self.new_point_distance_m}"
        )


def in_free_space(
    means_m: np.ndarray, ts: Timestamp, depths: dict[str, DepthMap], cfg: WarmStartConfig
) -> np.ndarray:
    """(N,) bool: the centre lies in front of the surface some stereo camera sees now."""
    gone = np.zeros(len(means_m), dtype=bool)
    for left, _right in ts.stereo_pairs():
        depth = depths.get(f"SN{left.camera_serial}")
        if depth is None:
            continue
        pose = left.camera.pose
        cam = means_m @ pose.R.T + pose.t_m  # world -> left sensor
        rect = cam @ depth.rect_from_left.T
        z = rect[:, 2]
        k = depth.intrinsics
        h, w = depth.depth_m.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(rect[:, 0] / z * k.fx_px + k.cx_px)
            v = np.round(rect[:, 1] / z * k.fy_px + k.cy_px)
        seen = (z > 0.05) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx = np.nonzero(seen)[0]
        ui, vi = u[idx].astype(int), v[idx].astype(int)
        valid = depth.valid[vi, ui]
        observed = depth.depth_m[vi, ui]
        margin = np.maximum(cfg.free_space_margin_m, cfg.free_space_margin_ratio * observed)
        gone[idx[valid & (z[idx] < observed - margin)]] = True
    return gone


def warm_seed(
    previous: Gaussians,
    ts: Timestamp,
    fused: FusedCloud,
    depths: dict[str, DepthMap],
    cfg: WarmStartConfig,
    init: GaussianInitConfig,
) -> tuple[Gaussians, dict[str, int]]:
    """The Gaussians t+1 starts from, and the counts (kept, dropped, added)."""
    means = previous.means_m.detach().cpu().numpy().astype(np.float64)
    gone = in_free_space(means, ts, depths, cfg)
    keep = torch.as_tensor(~gone)
    kept = Gaussians(**{k: v.detach()[keep].clone() for k, v in previous.parameters_dict().items()})
    points = np.asarray(fused.points_m, dtype=np.float64)
    added = 0
    parts = [kept]
    if len(points) and kept.num:
        # sliding-midpoint splits (scipy#5564): the median build segfaulted on a warm model's
        # positions, which compact storage keeps on a 0.24 mm grid, so many share a coordinate
        dist, _ = cKDTree(means[~gone], balanced_tree=False).query(points, k=1)
        new = dist > cfg.new_point_distance_m
    else:
        new = np.ones(len(points), dtype=bool)
    if new.sum() >= 4:  # nearest-neighbour scales need a few points
        fresh = init_from_points(points[new], np.asarray(fused.colours)[new], init)
        if fresh.sh_degree != kept.sh_degree:  # the previous model's degree wins
            fresh = Gaussians(
                **{**fresh.parameters_dict(), "sh_rest": torch.zeros_like(kept.sh_rest[:1])
                   .expand(fresh.num, -1, -1).clone()}
            )  # fmt: skip
        parts.append(fresh)
        added = fresh.num
    merged = Gaussians(
        **{
            name: torch.cat([getattr(p, name) for p in parts]).contiguous()
            for name in previous.parameters_dict()
        }
    )
    counts = {"kept": kept.num, "dropped": int(gone.sum()), "added": added}
    log.info("warm start: kept %(kept)d, dropped %(dropped)d, added %(added)d Gaussians", counts)
    return merged, counts


def warm_config(config: ReconstructConfig, warm: WarmStartConfig) -> ReconstructConfig:
    """A warm timestamp's settings: ``warm.steps`` on the input views, no auxiliary views
    (the case's warm timestamps and the evaluation's warm row use this one definition)."""
    train = dataclasses.replace(config.train, warmup_steps=warm.steps, refine_steps=0)
    aux = dataclasses.replace(config.auxiliary, enabled=False)
    return dataclasses.replace(config, train=train, auxiliary=aux)
