"""Training Gaussians on posed views with the paper's losses and schedule.

Loss, per step on one view (paper, "Implementation Details", plus a needle term)::

    L = (1 - α) · L1 + α · (1 - SSIM) + λ · mean(sigmoid(opacity)) + μ · needle,
    α = 0.2, λ = 0.05 (the paper: 0.2), μ = 10 (the paper: none)

``needle`` is ``anisotropy_penalty``. λ and μ were chosen on the simulated OR's egocentric
views (docs/reconstruct.md, "Schedule"): at the paper's λ, Adam drove most Gaussians
transparent and a few hundred grew metres long to paint what they left, a fog from any eye
inside the room; needles that fit the wall cameras, which look along them, are streaks from
elsewhere. The paper's loss: ``opacity_reg_weight = 0.2``, ``anisotropy_reg_weight = 0``.

No densification, splitting or pruning: the depth initialisation already places one Gaussian per
fused point. Backgrounds are random colours each step, so that the model cannot paint the
background into semi-transparent Gaussians. Adam with the usual 3DGS learning rates; the
position rate (1.6e-4) is multiplied by the scene extent, as 3DGS does, and decays exponentially
to 1 % of itself over the whole schedule.

The schedule is stages of steps: 500 warm-up steps on the input views, then 1500 steps on the
input views plus any auxiliary views the refinement stage adds, each view's image loss scaled
by its weight (``Trainer.run(..., weights=...)``; auxiliary views: ``auxiliary.aux_weight``).
One ``Trainer`` keeps the optimiser state across stages.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from reconstructor.data.views import View
from reconstructor.errors import ReconstructConfigError
from reconstructor.raster import RasterConfig, RenderOutput, rasterize
from reconstructor.splats.denormals import denormals_flushed_on_all_threads, flush_denormals
from reconstructor.splats.depth_term import depth_loss, rendered_depth
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.image_loss import image_loss

# the stage a step belongs to, in the log and the progress callback
TrainStage = Literal["train", "warm-up", "refinement"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    warmup_steps: int = 500
    refine_steps: int = 1500  # on the input views alone until a refiner adds auxiliary views
    ssim_weight: float = 0.2  # α
    opacity_reg_weight: float = 0.05  # λ (the paper: 0.2; see the module docstring)
    position_lr: float = 1.6e-4  # times the scene extent in metres, as 3DGS
    position_lr_final_ratio: float = 0.01
    sh_dc_lr: float = 2.5e-3
    sh_rest_lr: float = 2.5e-3 / 20
    opacity_lr: float = 0.05
    scale_lr: float = 5e-3
    rotation_lr: float = 1e-3
    random_background: bool = True
    # not in the paper: a Gaussian longer than anisotropy_max_ratio times its middle axis pays
    # anisotropy_reg_weight x the log of the excess (0: off). Needles that fit the few input
    # views show as streaks from far-off viewpoints (EVALUATION.md, egocentric views)
    anisotropy_max_ratio: float = 4.0
    anisotropy_reg_weight: float = 10.0
    # not in the paper: weight of the depth term on input views with a stereo depth target
    # (splats/depth_term.py). 0: off
    depth_weight: float = 0.0
    # 0: |D - alpha t| / t everywhere stereo answered (also asks for coverage there); > 0: the
    # depth error |D / alpha - t| / t only where the render covers at least this
    depth_min_alpha: float = 0.0
    seed: int = 0
    log_every_steps: int = 100

    def __post_init__(self) -> None:
        for name in ("warmup_steps", "refine_steps"):
            if getattr(self, name) < 0:
                raise ReconstructConfigError(
                    f"train.{name} must be >= 0, got {getattr(self, name)}"
                )
        if not 0.0 <= self.depth_min_alpha < 1.0:
            raise ReconstructConfigError(
                f"train.depth_min_alpha must be in [0, 1), got {self.depth_min_alpha}"
            )
        if not (self.depth_weight >= 0 and math.isfinite(self.depth_weight)):
            raise ReconstructConfigError(
                f"train.depth_weight must be a finite number >= 0, got {self.depth_weight}"
            )
        if self.warmup_steps + self.refine_steps == 0:
            raise ReconstructConfigError("train: warmup_steps + refine_steps must be at least 1")
        if not 0.0 <= self.ssim_weight <= 1.0:
            raise ReconstructConfigError(
                f"train.ssim_weight must be in [0, 1], got {self.ssim_weight}"
            )
        for name in (
            "position_lr",
            "sh_dc_lr",
            "sh_rest_lr",
            "opacity_lr",
            "scale_lr",
            "rotation_lr",
            "opacity_reg_weight",
            "anisotropy_reg_weight",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ReconstructConfigError(f"train.{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.anisotropy_max_ratio) and self.anisotropy_max_ratio >= 1):
            raise ReconstructConfigError(
                f"train.anisotropy_max_ratio must be >= 1, got {self.anisotropy_max_ratio}"
            )
        if not 0 < self.position_lr_final_ratio <= 1:
            raise ReconstructConfigError(
                "train.position_lr_final_ratio must be in (0, 1], got "
                f"{self.position_lr_final_ratio}"
            )

    @property
    def total_steps(self) -> int:
        return self.warmup_steps + self.refine_steps


@dataclass
class StepStats:
    step: int
    loss: float
    l1: float
    ssim: float
    view: str
    seconds: float


@dataclass
class TrainLog:
    steps: list[StepStats] = field(default_factory=list)

    def mean_loss(self, last: int = 50) -> float:
        tail = self.steps[-last:]
        return float(np.mean([s.loss for s in tail])) if tail else float("nan")

    @property
    def seconds(self) -> float:
        return float(sum(s.seconds for s in self.steps))


def scene_extent_m(views: Sequence[View]) -> float:
    """3DGS's spatial scale: 1.1 x the largest distance of a camera from the cameras' centre."""
    centres = np.array([v.pose.centre_m for v in views])
    mid = centres.mean(axis=0)
    return float(1.1 * max(np.linalg.norm(centres - mid, axis=1).max(), 0.1))


def render(
    gaussians: Gaussians,
    view: View,
    raster: RasterConfig,
    background: torch.Tensor | None = None,
) -> RenderOutput:
    """Render ``gaussians`` into ``view``'s camera; the outputs are on the CPU, for callers that
    read pixels, whichever device ``raster`` computes on (the model may sit on either)."""
    dev = gaussians.means_m.device
    bg = torch.zeros(3, device=dev) if background is None else background.to(dev)
    out = _rasterize(gaussians, view.viewmat, view.K, view.width_px, view.height_px, bg, raster)
    if out.image.device.type == "cpu":
        return out
    return RenderOutput(*(t.cpu() for t in (out.image, out.alpha, out.depth_m, out.radii_px)))


def _rasterize(
    g: Gaussians,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width_px: int,
    height_px: int,
    background: torch.Tensor,
    raster: RasterConfig,
) -> RenderOutput:
    return rasterize(
        g.means_m, g.quats_wxyz, g.log_scales, g.opacity_logits, g.colors(),
        viewmat, K, width_px, height_px, background, raster,
    )  # fmt: skip


@dataclass(frozen=True)
class _DeviceView:
    """A training view's tensors on the trainer's device (copied there once per run)."""

    view: View  # kept alive, so that its id() is not reused while this entry exists
    image: torch.Tensor
    mask: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor


class Trainer:
    """Adam over the Gaussians' parameters, kept across the stages of a schedule.

    On a GPU backend (``raster.device == "cuda"``) the trainer moves the model's tensors to the
    GPU in place (``gaussians`` then lives there; ``Gaussians.to`` brings a copy back) and each
    view's image, mask and camera the first time it is drawn: the loss, the rasterizer and Adam
    all run there, and only the random background (3 floats) and the logged values cross.
    """

    def __init__(
        self,
        gaussians: Gaussians,
        config: TrainConfig,
        raster: RasterConfig,
        extent_m: float,
    ) -> None:
        self.g = gaussians
        self.config = config
        self.raster = raster
        self.device = torch.device(raster.device)
        if self.device.type != "cpu":
            from reconstructor.raster.gsplat_backend import require_gpu

            require_gpu()
            gaussians.move_to(self.device)
        self._device_views: dict[int, _DeviceView] = {}
        self._depth_targets: dict[str, torch.Tensor] = {}
        self.step_index = 0
        self.log = TrainLog()
        self._rng = np.random.default_rng(config.seed)
        self._bg_gen = torch.Generator().manual_seed(config.seed)
        params = [
            ("means_m", config.position_lr * extent_m),
            ("sh_dc", config.sh_dc_lr),
            ("sh_rest", config.sh_rest_lr),
            ("opacity_logits", config.opacity_lr),
            ("log_scales", config.scale_lr),
            ("quats_wxyz", config.rotation_lr),
        ]
        groups = []
        for name, lr in params:
            t = getattr(gaussians, name)
            t.requires_grad_(True)
            if t.numel():
                groups.append({"params": [t], "lr": lr, "name": name})
        self._position_lr0 = config.position_lr * extent_m
        # fused: one kernel over all tensors, 5x faster than the default loop on a CPU
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)
        # Adam's moments of faded Gaussians decay into float32 denormals, 10x slower to
        # compute with: they must be flushed on every thread (reconstructor/splats/denormals.py).
        if flush_denormals() and not denormals_flushed_on_all_threads():
            log.warning(
                "float32 denormals are not flushed on torch's worker threads, so training slows "
                "down late in a long schedule (Adam up to 8x): torch started its threads before "
                "reconstructor was imported; import reconstructor before running torch operations"
            )

    def set_depth_targets(self, targets: Mapping[str, np.ndarray]) -> None:
        """Stereo depth targets (H, W) by view name (``depth.reproject.depth_targets``); the
        depth term uses them when ``depth_weight`` > 0. Views not named here have none."""
        self._depth_targets = {
            name: torch.as_tensor(t, dtype=torch.float32).to(self.device)
            for name, t in targets.items()
        }

    def _position_lr(self) -> float:
        total = max(self.config.total_steps, 1)
        u = min(self.step_index / total, 1.0)
        return self._position_lr0 * self.config.position_lr_final_ratio**u

    def step(self, view: View, weight: float = 1.0) -> StepStats:
        """One Adam step on ``view``; ``weight`` scales its image loss (not the opacity term)."""
        t0 = time.perf_counter()
        cfg = self.config
        for group in self.optimizer.param_groups:
            if group["name"] == "means_m":
                group["lr"] = self._position_lr()
        if cfg.random_background:
            bg = torch.rand(3, generator=self._bg_gen)
        else:
            bg = torch.zeros(3)
        dv = self._on_device(view)
        bg = bg.to(self.device)
        out = _rasterize(self.g, dv.viewmat, dv.K, view.width_px, view.height_px, bg, self.raster)
        # where the recorded image has no content, compare against the background itself
        image_term, l1_v, ssim_v = image_loss(out.image, dv.image, dv.mask, cfg.ssim_weight, bg)
        loss = weight * image_term
        if cfg.opacity_reg_weight > 0 and self.g.num > 0:
            loss = loss + cfg.opacity_reg_weight * torch.sigmoid(self.g.opacity_logits).mean()
        if cfg.anisotropy_reg_weight > 0 and self.g.num > 0:
            loss = loss + cfg.anisotropy_reg_weight * anisotropy_penalty(
                self.g.log_scales, cfg.anisotropy_max_ratio
            )
        target = self._depth_targets.get(view.name) if cfg.depth_weight > 0 else None
        if target is not None and self.g.num > 0:
            d, a = rendered_depth(self.g, dv.viewmat, dv.K, view.width_px, view.height_px,
                                  self.raster)  # fmt: skip
            loss = loss + weight * cfg.depth_weight * depth_loss(d, a, target, cfg.depth_min_alpha)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.step_index += 1
        stats = StepStats(
            step=self.step_index,
            loss=float(loss.detach()),
            l1=float(l1_v.detach()),
            ssim=float(ssim_v.detach()),
            view=view.name,
            seconds=time.perf_counter() - t0,
        )
        self.log.steps.append(stats)
        return stats

    def _on_device(self, view: View) -> _DeviceView:
        """``view``'s tensors on the trainer's device; on the CPU, the view's own."""
        if self.device.type == "cpu":
            return _DeviceView(view, view.image, view.mask, view.viewmat, view.K)
        dv = self._device_views.get(id(view))
        if dv is None:
            dev = self.device
            dv = _DeviceView(
                view,
                view.image.to(dev),
                view.mask.to(dev),
                view.viewmat.to(dev, torch.float32),
                view.K.to(dev, torch.float32),
            )
            self._device_views[id(view)] = dv
        return dv

    def run(
        self,
        views: Sequence[View],
        steps: int,
        *,
        stage: TrainStage = "train",
        progress: Callable[[str, int, int, StepStats], None] | None = None,
        weights: Sequence[float] | None = None,
    ) -> None:
        """``steps`` steps, each on a view drawn from shuffled passes over ``views``.

        ``weights``: one loss weight per view (default 1; auxiliary views may weigh less).
        """
        if not views:
            raise ReconstructConfigError(f"{stage}: no views to train on")
        if weights is not None and len(weights) != len(views):
            raise ValueError(f"{stage}: {len(weights)} weights for {len(views)} views")
        order: list[int] = []
        for k in range(steps):
            if not order:
                order = list(self._rng.permutation(len(views)))
            i = order.pop()
            stats = self.step(views[i], 1.0 if weights is None else weights[i])
            if progress is not None:
                progress(stage, k + 1, steps, stats)
            self._log_step(stage, k + 1, steps, stats)

    def _log_step(self, stage: TrainStage, k: int, steps: int, stats: StepStats) -> None:
        if cfg_log(self.config, k, steps):
            log.info(
                "%s step %d/%d: loss %.4f (L1 %.4f, SSIM %.4f), %.0f ms/step",
                stage,
                k,
                steps,
                self.log.mean_loss(self.config.log_every_steps),
                stats.l1,
                stats.ssim,
                1000 * stats.seconds,
            )

    def run_mixed(
        self,
        groups: Sequence[ViewGroup],
        steps: int,
        *,
        stage: TrainStage = "train",
        progress: Callable[[str, int, int, StepStats], None] | None = None,
    ) -> None:
        """``steps`` steps drawn from ``groups`` in proportion to their shares (each step goes to
        the group furthest behind its share; within a group, shuffled passes over its views).

        The refinement stage trains on the recorded views and on many more auxiliary views; a
        share keeps the recorded views' part of the steps fixed however many auxiliary views
        there are.
        """
        groups = [g for g in groups if g.views and g.share > 0]
        if not groups:
            raise ReconstructConfigError(f"{stage}: no views to train on")
        orders: list[list[int]] = [[] for _ in groups]
        for k, j in enumerate(mixed_schedule([g.share for g in groups], steps)):
            if not orders[j]:
                orders[j] = list(self._rng.permutation(len(groups[j].views)))
            stats = self.step(groups[j].views[orders[j].pop()], groups[j].weight)
            if progress is not None:
                progress(stage, k + 1, steps, stats)
            self._log_step(stage, k + 1, steps, stats)


def mixed_schedule(shares: Sequence[float], steps: int) -> list[int]:
    """The group each of ``steps`` steps goes to (``Trainer.run_mixed``): the group furthest
    behind its share (``shares``, positive, in any units) after the steps before it, the first
    on a tie. Deterministic, so a run's steps per group are known before it starts: with shares
    0.95 / 0.05 the second group gets its first step at the 11th."""
    if not shares or any(not share > 0 for share in shares):
        raise ValueError(f"shares {list(shares)}: give one positive share per group")
    total = float(sum(shares))
    done = [0] * len(shares)
    out = []
    for k in range(steps):
        j = max(range(len(shares)), key=lambda i: shares[i] / total * (k + 1) - done[i])
        done[j] += 1
        out.append(j)
    return out


def anisotropy_penalty(log_scales: torch.Tensor, max_ratio: float) -> torch.Tensor:
    """Mean over Gaussians of max(0, ln(largest / middle axis) - ln(max_ratio)).

    A flat disc (two long axes, one short) is free, as surfaces need; a needle (one axis much
    longer than the other two) pays for its length beyond ``max_ratio`` times its width.
    """
    top2 = torch.topk(log_scales, 2, dim=1).values
    return torch.relu(top2[:, 0] - top2[:, 1] - math.log(max_ratio)).mean()


@dataclass(frozen=True)
class ViewGroup:
    """Views drawn together: ``share`` of the steps, each step's loss times ``weight``."""

    views: Sequence[View]
    share: float
    weight: float = 1.0


def cfg_log(config: TrainConfig, k: int, steps: int) -> bool:
    every = max(config.log_every_steps, 1)
    return k % every == 0 or k == steps
