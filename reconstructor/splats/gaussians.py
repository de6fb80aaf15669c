"""The Gaussian splat model as tensors, and its initialisation from a fused point cloud.

Parameters are stored raw, as 3DGS optimises and stores them (and as the INRIA PLY holds them):

- ``means_m`` (N, 3): centres in world metres;
- ``quats_wxyz`` (N, 4): rotations, w first, not necessarily normalised;
- ``log_scales`` (N, 3): natural logs of the standard deviations along the local axes, metres;
- ``opacity_logits`` (N,): opacity = sigmoid(logit);
- ``sh_dc`` (N, 3): degree-0 SH coefficient per channel, colour = 0.5 + C0 · sh_dc;
- ``sh_rest`` (N, K, 3): the higher SH coefficients, K = (d + 1)² − 1 (0 for degree 0).

Initialisation follows 3DGS: identity rotation, opacity 0.1, isotropic scale from the distance
to the 3 nearest neighbours (its ``distCUDA2``: scale = sqrt(mean of the 3 squared distances)),
colour into ``sh_dc``, higher SH zero. ``init_random`` (the "image-only 3DGS" baseline) draws
the points and colours uniformly in a box instead, then initialises them the same way.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
from scipy.spatial import cKDTree

from reconstructor.data.views import View
from reconstructor.errors import ReconstructConfigError

log = logging.getLogger(__name__)

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)): the degree-0 real spherical harmonic
MAX_SH_DEGREE = 3


@dataclass(frozen=True, kw_only=True)
class GaussianInitConfig:
    opacity: float = 0.1  # 3DGS's initial opacity
    sh_degree: int = 0  # the paper trains with degree-0 SH
    neighbours: int = 3
    min_scale_m: float = 3e-4  # 3DGS clamps the squared distance at 1e-7 m², ~0.3 mm
    max_scale_m: float = 0.1  # an isolated point must not start as a room-sized blob

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ReconstructConfigError:
            return ReconstructConfigError(
                f"GaussianInitConfig.{name}={getattr(self, name)!r}: {why}"
            )

        if not 0.0 < self.opacity < 1.0:
            raise bad("opacity", "must be strictly between 0 and 1")
        if not 0 <= self.sh_degree <= MAX_SH_DEGREE:
            raise bad("sh_degree", f"must be 0 to {MAX_SH_DEGREE}")
        if self.neighbours < 1:
            raise bad("neighbours", "must be at least 1")
        if not 0.0 < self.min_scale_m <= self.max_scale_m:
            raise bad("min_scale_m", f"must be positive and <= max_scale_m={self.max_scale_m!r}")


def num_sh_rest(degree: int) -> int:
    """K, the number of SH coefficients per channel above degree 0."""
    return (degree + 1) ** 2 - 1


@dataclass(eq=False)
class Gaussians:
    """N Gaussians as float tensors on one device (see the module docstring for each field)."""

    means_m: torch.Tensor
    quats_wxyz: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means_m.shape[0]
        expected = {
            "means_m": (n, 3),
            "quats_wxyz": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
            "sh_dc": (n, 3),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name} has shape {got}, expected {shape}")
        rest = tuple(self.sh_rest.shape)
        if len(rest) != 3 or rest[0] != n or rest[2] != 3 or _degree(rest[1]) is None:
            raise ValueError(
                f"Gaussians.sh_rest has shape {rest}, expected ({n}, K, 3) with K = (d+1)²-1"
            )

    @property
    def num(self) -> int:
        return int(self.means_m.shape[0])

    @property
    def sh_degree(self) -> int:
        d = _degree(self.sh_rest.shape[1])
        assert d is not None  # checked in __post_init__
        return d

    def colors(self) -> torch.Tensor:
        """(N, 3) RGB of the degree-0 term, 0.5 + C0 · sh_dc (not clamped)."""
        return 0.5 + SH_C0 * self.sh_dc

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def scales_m(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def parameters_dict(self) -> dict[str, torch.Tensor]:
        """Field name -> tensor, in a fixed order (for optimisers and checkpoints)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to(
        self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> Gaussians:
        return Gaussians(**{k: v.to(dtype=dtype, device=device) for k, v in self._items()})

    def move_to(self, device: torch.device | str) -> None:
        """Move every tensor to ``device`` in place (leaf tensors keep requires_grad)."""
        for name, t in self._items():
            moved = t.detach().to(device)
            setattr(self, name, moved.requires_grad_(t.requires_grad))

    def detach_clone(self) -> Gaussians:
        return Gaussians(**{k: v.detach().clone() for k, v in self._items()})

    def _items(self) -> list[tuple[str, torch.Tensor]]:
        return list(self.parameters_dict().items())


def _degree(k: int) -> int | None:
    d = math.isqrt(k + 1) - 1
    return d if (d + 1) ** 2 == k + 1 else None


def init_from_points(
    points_m: np.ndarray, colours: np.ndarray, config: GaussianInitConfig | None = None
) -> Gaussians:
    """Gaussians seeded at ``points_m`` (N, 3) with ``colours`` (N, 3) in 0..1."""
    cfg = config or GaussianInitConfig()
    pts = np.asarray(points_m, dtype=np.float64)
    cols = np.asarray(colours, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or cols.shape != pts.shape or not len(pts):
        raise ValueError(
            f"points {pts.shape} and colours {cols.shape} must both be (N, 3) with N >= 1"
        )
    scale = nearest_neighbour_scale(pts, cfg.neighbours)
    scale = np.clip(scale, cfg.min_scale_m, cfg.max_scale_m)
    n = len(pts)
    f32 = torch.float32
    logit = math.log(cfg.opacity / (1.0 - cfg.opacity))
    quats = torch.zeros((n, 4), dtype=f32)
    quats[:, 0] = 1.0
    log.info("initialised %d Gaussians (median scale %.4f m)", n, float(np.median(scale)))
    return Gaussians(
        means_m=torch.as_tensor(pts, dtype=f32),
        quats_wxyz=quats,
        log_scales=torch.as_tensor(np.log(scale), dtype=f32)[:, None].repeat(1, 3),
        opacity_logits=torch.full((n,), logit, dtype=f32),
        sh_dc=torch.as_tensor((cols - 0.5) / SH_C0, dtype=f32),
        sh_rest=torch.zeros((n, num_sh_rest(cfg.sh_degree), 3), dtype=f32),
    )


def nearest_neighbour_scale(points_m: np.ndarray, k: int = 3) -> np.ndarray:
    """(N,) sqrt of the mean squared distance to each point's ``k`` nearest other points
    (3DGS's ``distCUDA2``); inf for a lone point."""
    n = len(points_m)
    if n < 2:
        return np.full(n, np.inf)
    k_eff = min(k, n - 1)
    # sliding-midpoint splits (balanced_tree=False): the median build can recurse without end
    # on many points sharing a coordinate (scipy#5564) and overflow the stack. It segfaulted on
    # a room cloud whose stereo points had been moved onto the wall planes (a tried change)
    tree = cKDTree(points_m, balanced_tree=False)
    dist, _ = tree.query(points_m, k=k_eff + 1, workers=-1)
    dist = np.asarray(dist).reshape(n, k_eff + 1)[:, 1:]  # column 0 is the point itself
    return np.sqrt(np.mean(dist**2, axis=1))


def init_random(
    count: int,
    lo_m: np.ndarray,
    hi_m: np.ndarray,
    config: GaussianInitConfig | None = None,
    *,
    seed: int = 0,
) -> Gaussians:
    """``count`` Gaussians uniform in the box ``lo_m``..``hi_m`` (3,) with uniform random colours:
    the paper's "image-only 3DGS" baseline (no stereo depth), initialised as gsplat's trainer
    does its random start; scales, opacity and rotations as ``init_from_points``."""
    lo = np.asarray(lo_m, dtype=np.float64).reshape(3)
    hi = np.asarray(hi_m, dtype=np.float64).reshape(3)
    if count < 1:
        raise ReconstructConfigError(f"random_init_count={count}: must be at least 1")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ReconstructConfigError(
            f"random init box {lo.tolist()}..{hi.tolist()} m: needs finite corners, lo < hi"
        )
    rng = np.random.default_rng(seed)
    points = rng.uniform(lo, hi, size=(count, 3))
    colours = rng.uniform(0.0, 1.0, size=(count, 3))
    log.info(
        "random init: %d Gaussians in the box %s..%s m",
        count,
        np.round(lo, 2).tolist(),
        np.round(hi, 2).tolist(),
    )
    return init_from_points(points, colours, config)


def random_init_box(
    views: Sequence[View],
    bounds: tuple[np.ndarray, np.ndarray] | None,
    *,
    fallback_depth_m: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the random init: the bounds where finite, else the box the cameras look into.

    That box holds the cameras' centres and their frustums' centre and corner rays out to the
    depth of the point closest to all optical axes (in the least-squares sense), or out to
    ``fallback_depth_m`` when the axes do not converge (one camera, parallel axes).
    """
    centres = np.array([v.pose.centre_m for v in views])
    forwards = np.array([v.pose.R[2] for v in views])
    A = sum((np.eye(3) - np.outer(f, f) for f in forwards), np.zeros((3, 3)))
    b = sum(((np.eye(3) - np.outer(f, f)) @ c for f, c in zip(forwards, centres, strict=True)))
    depths = np.full(len(views), fallback_depth_m)
    if len(views) > 1 and np.linalg.eigvalsh(A)[0] > 1e-2 * len(views):
        meet = np.linalg.solve(A, b)
        along = np.einsum("ij,ij->i", meet - centres, forwards)
        depths = np.where(along > 0.5, along, fallback_depth_m)
    points = [centres]
    for v, d in zip(views, depths, strict=True):
        w, h = v.width_px, v.height_px
        px = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1], [w / 2, h / 2, 1]], float)
        rays_cam = px @ np.linalg.inv(v.K.double().numpy()).T  # z = 1: camera-z depth d below
        points.append(v.pose.centre_m + d * rays_cam @ v.pose.R)
    cloud = np.concatenate(points)
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    if bounds is not None:
        lo = np.where(np.isfinite(bounds[0]), bounds[0], lo)
        hi = np.where(np.isfinite(bounds[1]), bounds[1], hi)
    return lo, hi
