"""The methods of the paper's Tables 3 and 4, and the settings of an evaluation run.

Methods (``--methods`` keys), each a switch of ``ReconstructConfig`` (see config.py):

- ``depth-reprojection``: every valid pixel of every stereo depth map drawn straight into the
  target camera, holes left as holes and counted (``baselines.reproject_depth_maps``); no
  training. It reuses the depth maps of a depth-initialised run of the same timestamp, or runs
  stereo alone;
- ``image-only``: "image-only 3DGS": ``init_method = "random"``, no auxiliary views;
- ``no-refinement``: "EgoSurg w/o refinement" (the paper's "w/o diffusion"): depth init,
  ``auxiliary.enabled = false``;
- ``egosurg``: the full method: depth init and auxiliary views refined by ``--refiner``;
- ``egosurg-eye`` (not one of the paper's rows): EgoSurg with 24 auxiliary cameras
  more, at standing and seated eye height inside the room (``refine/eye_views.py``), each
  refined against the recorded views that see what it looks at;
- ``egosurg-warm`` (not one of the paper's rows; temporal protocol only): a case's warm start
  (``reconstructor/case/warm.py``). A sequence's first frame is EgoSurg's cold model;
  each later frame starts from the previous frame's warm model, drops what the new stereo depth
  shows to be gone, seeds what is new and trains ``--warm-steps`` on the input views, as
  ``egosurg reconstruct --every ... --warm-start`` does.

``--steps`` is the total schedule, split 25 % warm-up and 75 % refinement like the paper's
500 + 1500.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from protocol.camera import Pose
from protocol.command import CommandArgumentError
from reconstructor.case.warm import WarmStartConfig
from reconstructor.config import ReconstructConfig
from reconstructor.data.views import View
from reconstructor.depth.stereo import DepthMap
from reconstructor.evaluation.baselines import reproject_depth_maps
from reconstructor.raster.config import RasterConfig
from reconstructor.raster.device import for_device
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import mixed_schedule, render


@dataclass(frozen=True)
class Method:
    key: str  # the ``--methods`` name
    label: str  # the paper's row name
    overrides: dict[str, Any] | None  # config changes; None: no training (depth reprojection)
    warm: bool = False  # frames after a sequence's first start from the previous frame's model

    @property
    def trained(self) -> bool:
        return self.overrides is not None

    @property
    def depth_init(self) -> bool:
        return self.overrides is not None and self.overrides.get("init_method", "depth") == "depth"


METHODS: dict[str, Method] = {
    m.key: m
    for m in (
        Method("depth-reprojection", "Depth reprojection", None),
        Method(
            "image-only",
            "Image-only 3DGS",
            {"init_method": "random", "auxiliary": {"enabled": False}},
        ),
        Method(
            "no-refinement",
            "EgoSurg w/o refinement",
            {"init_method": "depth", "auxiliary": {"enabled": False}},
        ),
        Method("egosurg", "EgoSurg", {"init_method": "depth", "auxiliary": {"enabled": True}}),
        Method(
            "egosurg-eye",
            "EgoSurg + eye-height views",
            {"init_method": "depth", "auxiliary": {"enabled": True, "eye": {"num_views": 24}}},
        ),
        Method(
            "egosurg-warm",
            "EgoSurg (warm start)",
            {"init_method": "depth", "auxiliary": {"enabled": True}},
            warm=True,
        ),
    )
}
# worst to best, as the paper reports them; the default ``--methods``
PAPER_ORDER = ("depth-reprojection", "image-only", "no-refinement", "egosurg")
ProtocolName = Literal["near-field", "egocentric", "temporal", "phases"]
PROTOCOLS: tuple[ProtocolName, ...] = typing.get_args(ProtocolName)


@dataclass(frozen=True, kw_only=True)
class EvalSettings:
    """Everything that decides an evaluation's numbers; printed in every table's header.

    The scenes, their instants and the reference views come from the evaluation set
    (``protocol.formats.eval_set``); ``scenes`` and ``phases`` only choose among its scenes.
    """

    eval_set: str = ""  # the evaluation set's folder, as given
    eval_set_description: str = ""  # its manifest's description: how it was made
    protocols: tuple[ProtocolName, ...] = ("near-field",)
    methods: tuple[str, ...] = PAPER_ORDER
    warm_steps: int = WarmStartConfig.steps  # training steps of a warm frame (egosurg-warm)
    scenes: tuple[str, ...] = ()  # scene names to use; () = every scene of the set
    phases: tuple[str, ...] = ()  # phases to use; () = every phase
    steps: int = 2000
    train_width_px: int = 960
    refiner: str = "guided"
    refiner_weights: str = ""
    lpips_weights: str = ""
    config: str = ""  # a reconstruction config (TOML) every method starts from; "" = defaults
    device: str = ""  # "cuda": train and render on gsplat's CUDA backend; "" = as the config says

    def __post_init__(self) -> None:
        def bad(option: str, value: object, why: str) -> CommandArgumentError:
            return CommandArgumentError(f"{option} {value}: {why}")

        for p in self.protocols:
            if p not in PROTOCOLS:
                raise bad("--protocol", p, f"choose from {', '.join(PROTOCOLS)} or all")
        if not self.methods:
            raise bad("--methods", "(none)", f"name at least one of {', '.join(METHODS)}")
        for m in self.methods:
            if m not in METHODS:
                raise bad("--methods", m, f"choose from {', '.join(METHODS)}")
        if self.steps < 1:
            raise bad("--steps", self.steps, "must be at least 1 (the paper uses 2000)")
        if self.warm_steps < 1:
            raise bad("--warm-steps", self.warm_steps, "must be at least 1 (3DGStream: 250)")
        if self.has_warm and "temporal" not in self.protocols:
            raise bad("--methods", "egosurg-warm", "continues a sequence: add --protocol temporal")
        if self.train_width_px < 64:
            raise bad("--train-width", self.train_width_px, "must be at least 64 px")

    @property
    def warmup_steps(self) -> int:
        return int(0.25 * self.steps + 0.5)  # half up: 10 steps are 3 + 7, not 2 + 8

    @property
    def refine_steps(self) -> int:
        return self.steps - self.warmup_steps

    @property
    def uses_refiner(self) -> bool:
        """Whether a chosen method makes auxiliary views (and so runs the refiner)."""
        return any(
            (METHODS[m].overrides or {}).get("auxiliary", {}).get("enabled", False)
            for m in self.methods
            if m in METHODS
        )

    def _refinement_shares(self, key: str) -> tuple[list[float], list[int]] | None:
        """The refinement's groups for method ``key`` as ``Trainer.run_mixed`` gets them: their
        shares, and which of them are the refiner's views (index > 0); None without them."""
        overrides = METHODS[key].overrides
        if not (overrides or {}).get("auxiliary", {}).get("enabled", False):
            return None
        cfg = ReconstructConfig.read(self.config) if self.config else ReconstructConfig()
        aux = cfg.overridden(overrides or {}, f"method {key}").auxiliary
        if aux.input_share <= 0:  # every step draws from all views alike: no fixed count
            return None
        shares = aux.refinement_shares(aux.eye.num_views > 0)
        groups = [k for k, share in enumerate(shares) if share > 0]
        return [shares[k] for k in groups], groups

    def auxiliary_steps(self, key: str) -> int | None:
        """How many of method ``key``'s refinement steps train on the refiner's views (its
        auxiliary and eye-height views); None for a method without them, or where every step
        draws from all views alike (``auxiliary.input_share`` 0). The recorded views keep
        ``input_share`` of the steps (0.95), so a short schedule may give the refiner none."""
        found = self._refinement_shares(key)
        if found is None:
            return None
        shares, groups = found
        return sum(groups[j] > 0 for j in mixed_schedule(shares, self.refine_steps))

    def steps_for_auxiliary(self, key: str) -> int:
        """The fewest ``--steps`` at which method ``key`` trains on one of the refiner's views
        (the schedule's steps come in the same order however long it is)."""
        found = self._refinement_shares(key)
        if found is None:
            return self.steps
        shares, groups = found
        first = next(
            (k for k, j in enumerate(mixed_schedule(shares, 100_000)) if groups[j] > 0), None
        )
        if first is None:
            return self.steps
        steps = 1
        while dataclasses.replace(self, steps=steps).refine_steps < first + 1:
            steps += 1
        return steps

    @property
    def has_warm(self) -> bool:
        return any(METHODS[m].warm for m in self.methods if m in METHODS)

    def label(self, key: str) -> str:
        if key == "egosurg":
            return f"EgoSurg ({self.refiner} refiner)"
        if METHODS[key].warm:
            return f"EgoSurg, warm start ({self.warm_steps} steps per later frame)"
        return METHODS[key].label

    def describe(self) -> str:
        """One line with every setting a reader needs to interpret the numbers."""
        refiner = self.refiner if self.uses_refiner else "n/a (EgoSurg not run)"
        on_aux = {
            m: n
            for m in self.methods
            if m in METHODS and (n := self.auxiliary_steps(m)) is not None
        }
        if on_aux:
            counts = sorted(set(on_aux.values()))
            refiner += (
                f" ({'/'.join(map(str, counts))} of the {self.refine_steps} refinement steps on "
                "its views)"
            )
        lpips = self.lpips_weights or "n/a (no --lpips-weights)"
        chosen = [
            f"scenes {', '.join(self.scenes)}" if self.scenes else "",
            f"phases {', '.join(self.phases)}" if self.phases else "",
        ]
        chosen = [c for c in chosen if c] or ["every scene"]
        which = "; ".join(c for c in [self.eval_set_description, *chosen] if c)
        return (
            f"steps {self.steps} ({self.warmup_steps} warm-up + {self.refine_steps} refinement), "
            f"training width {self.train_width_px} px, refiner {refiner}, "
            f"evaluation set {self.eval_set or '?'} ({which}), LPIPS weights {lpips}, "
            f"base config {self.config or 'the defaults'}"
            + (f", device {self.device}" if self.device else "")
            + (f", warm start {self.warm_steps} steps" if self.has_warm else "")
        )

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def method_config(
    settings: EvalSettings, key: str, train_views: str, room_bounds_m: tuple[float, ...]
) -> ReconstructConfig:
    """The reconstruction config of one trained method."""
    overrides = METHODS[key].overrides
    if overrides is None:
        raise ValueError(f"{key} is not trained")
    base: dict[str, Any] = {
        "train_views": train_views,
        "train_max_width_px": settings.train_width_px,
        "room_bounds_m": list(room_bounds_m),
        "train": {"warmup_steps": settings.warmup_steps, "refine_steps": settings.refine_steps},
        "auxiliary": {
            "refiner": settings.refiner,
            "refiner_weights": settings.refiner_weights,
            "save_pictures": False,
        },
    }
    start = ReconstructConfig.read(settings.config) if settings.config else ReconstructConfig()
    cfg = start.overridden(base, "evaluation settings")
    cfg = cfg.overridden(overrides, f"method {key}")
    if settings.device:
        cfg = dataclasses.replace(cfg, raster=for_device(cfg.raster, settings.device))
    return cfg


def render_splats(
    gaussians: Gaussians, raster: RasterConfig, view: View, near_m: float = 0.0
) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1]: the model seen from ``view`` over black, leaving out what
    is nearer than ``near_m`` (or the model's own near plane, whichever is further)."""
    if near_m > raster.near_m:
        raster = dataclasses.replace(raster, near_m=near_m)
    with torch.no_grad():
        out = render(gaussians, view, raster)
    return out.image.clamp(0, 1).numpy()


def render_depth_maps(
    sources: list[tuple[DepthMap, Pose]], view: View, near_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) float32 in [0, 1], holes (H, W) bool): the depth-reprojection baseline seen
    from ``view`` (every valid pixel of every depth map, ``baselines.reproject_depth_maps``)."""
    return reproject_depth_maps(sources, view.camera, near_m=near_m)
