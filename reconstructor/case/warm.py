"""Warm start: timestamp t+1 begins from t's trained Gaussians instead of from scratch.

What did not move is kept as trained. What t+1's stereo depth shows to be gone is dropped: a
Gaussian whose centre lies clearly in front of the surface a stereo camera now sees (free space
at t+1: a person walked away, the C-arm swung) cannot be there any more. So is a Gaussian that
training faded below the rasterizer's cut-off (``drop_opacity_below``): it draws nothing, yet
costs every step as much as a visible one. Where t+1's fused points lie outside every kept
Gaussian (someone arrived), new Gaussians are seeded from those points as a cold run seeds
them. "Outside" is measured in the nearest Gaussians' own shape (Mahalanobis distance), not in
metres alone: the same wall seen again gives a different stereo subsample, whose points fall
between the trained splats; seeded again each timestamp they would grow the model (and each
step's cost) without adding anything. Then training runs far fewer steps
(``WarmStartConfig.steps``), as Dynamic 3D Gaussians (Luiten et al.) and 3DGStream do.
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
    # a new point farther than this from every kept Gaussian's centre, and outside
    # ``cover_sigmas`` standard deviations of each of its nearest ones, is new content
    new_point_distance_m: float = 0.03
    cover_sigmas: float = 3.0
    # a kept Gaussian fainter than this is dropped: the rasterizer skips fragments below its
    # alpha_min (1/255), so it draws nothing
    drop_opacity_below: float = 1 / 255

    def __post_init__(self) -> None:
        if self.steps < 1 or self.keyframe_every < 1:
            raise ReconstructConfigError(
                f"warm start: steps={self.steps} and keyframe_every={self.keyframe_every} must "
                "both be at least 1"
            )
        if min(self.free_space_margin_m, self.new_point_distance_m) <= 0:
            raise ReconstructConfigError("warm start: the distances must be positive metres")
        if self.cover_sigmas < 0 or not 0 <= self.drop_opacity_below < 1:
            raise ReconstructConfigError(
                f"warm start: cover_sigmas={self.cover_sigmas} must be >= 0 and "
                f"drop_opacity_below={self.drop_opacity_below} in [0, 1)"
            )

    def describe(self) -> str:
        return (
            f"warm steps={self.steps} keyframe_every={self.keyframe_every} "
            f"margin={self.free_space_margin_m}/{self.free_space_margin_ratio} "
            f"new={self.new_point_distance_m}/{self.cover_sigmas}sd "
            f"faded<{self.drop_opacity_below:.4f}"
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


@dataclass(frozen=True, eq=False)
class WarmSeed:
    """What a warm timestamp starts from: ``gaussians`` (the kept rows of the previous model, in
    order, then the new seeds), ``alive`` ((N_previous,) bool: which previous rows were kept,
    for compact storage) and ``counts`` (kept, dropped, faded, added)."""

    gaussians: Gaussians
    alive: np.ndarray
    counts: dict[str, int]


def seed_from_previous(
    previous: Gaussians,
    ts: Timestamp,
    fused: FusedCloud,
    depths: dict[str, DepthMap],
    cfg: WarmStartConfig,
    init: GaussianInitConfig,
) -> WarmSeed:
    """The previous model without what is gone or faded, plus seeds where the scene is new."""
    means = previous.means_m.detach().cpu().numpy().astype(np.float64)
    gone = in_free_space(means, ts, depths, cfg)
    faded = previous.opacities().detach().cpu().numpy() < cfg.drop_opacity_below
    alive = ~(gone | faded)
    keep = torch.as_tensor(alive)
    kept = Gaussians(**{k: v.detach()[keep].clone() for k, v in previous.parameters_dict().items()})
    points = np.asarray(fused.points_m, dtype=np.float64)
    new = uncovered(points, kept, cfg) if kept.num else np.ones(len(points), dtype=bool)
    parts = [kept]
    added = 0
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
    counts = {
        "kept": kept.num,
        "dropped": int(gone.sum()),
        "faded": int((faded & ~gone).sum()),
        "added": added,
    }
    log.info(
        "warm start: kept %(kept)d, dropped %(dropped)d in free space and %(faded)d faded, "
        "added %(added)d Gaussians",
        counts,
    )
    return WarmSeed(gaussians=merged, alive=alive, counts=counts)


def uncovered(
    points_m: np.ndarray, kept: Gaussians, cfg: WarmStartConfig, k: int = 4
) -> np.ndarray:
    """(M,) bool: the point is farther than ``new_point_distance_m`` from every kept centre and
    outside ``cover_sigmas`` standard deviations of each of its ``k`` nearest Gaussians."""
    means = kept.means_m.detach().cpu().numpy().astype(np.float64)
    k = min(k, kept.num)
    # sliding-midpoint splits (scipy#5564): the median build segfaulted on a warm model's
    # positions, which compact storage keeps on a 0.24 mm grid, so many share a coordinate
    dist, idx = cKDTree(means, balanced_tree=False).query(points_m, k=k)
    dist, idx = dist.reshape(len(points_m), k), idx.reshape(len(points_m), k)
    new = dist[:, 0] > cfg.new_point_distance_m
    if cfg.cover_sigmas <= 0 or not new.any():
        return new
    rows = np.nonzero(new)[0]
    q = kept.quats_wxyz.detach().cpu().numpy().astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    inv_s = np.exp(-kept.log_scales.detach().cpu().numpy().astype(np.float64))
    nearest = idx[rows]  # (R, k)
    d = points_m[rows, None, :] - means[nearest]  # (R, k, 3) world offsets
    local = np.einsum("rkji,rkj->rki", _rotations(q[nearest]), d)  # into each Gaussian's axes
    mahalanobis = np.linalg.norm(local * inv_s[nearest], axis=2)
    new[rows] = (mahalanobis > cfg.cover_sigmas).all(axis=1)
    return new


def _rotations(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices (body -> world) of unit quaternions (..., 4) w, x, y, z."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def warm_config(config: ReconstructConfig, warm: WarmStartConfig) -> ReconstructConfig:
    """A warm timestamp's settings: ``warm.steps`` on the input views, no auxiliary views
    (the case's warm timestamps and the evaluation's warm row use this one definition).
    A warm timestamp never trains more steps than a cold one of the same config would: it
    starts from a trained model, so a short cold schedule (a quick look, a test) stays short."""
    cold_steps = config.train.warmup_steps + config.train.refine_steps
    steps = min(warm.steps, cold_steps)
    train = dataclasses.replace(config.train, warmup_steps=steps, refine_steps=0)
    aux = dataclasses.replace(config.auxiliary, enabled=False)
    return dataclasses.replace(config, train=train, auxiliary=aux)
