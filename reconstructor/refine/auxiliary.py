"""Auxiliary views for the refinement stage (paper, "Diffusion-augmented view refinement").

After warm-up, for each input camera:

1. render the current model from the input camera itself: its depth is the reference depth a
   refiner uses to tell occluded pixels apart, and its median (where alpha > 0.5) is the
   look-at depth below (at least 2 R), unless ``look_at_depth_m`` fixes one;
2. sample ``num_views`` (N = 15) camera centres around it, ``min_radius_m <= |d| <= radius_m``
   (R = 0.4 m) with ``d · forward >= 0`` (the half ball on the scene's side of the camera),
   uniform in volume, inside the room's bounds when they are known;
3. each auxiliary camera looks at the point the input camera looks at (the look-at depth along
   its optical axis), keeps the input's intrinsics, and takes its image-up from the input
   camera's image-up, so it never rolls over;
4. render the model there (image, alpha, depth over a black background), hand render and
   reference (the input view's recorded image and mask) to the refiner, and keep the refined
   image and mask as a training view named ``aux:<input>:<k>``.

The views are made once, after warm-up, and train with the input views for the rest of the
schedule; ``aux_weight`` scales their loss relative to an input view's (the paper is silent:
1.0), and ``input_share`` keeps 95 % of the refinement steps on the recorded views (the paper is
silent; drawn uniformly, 4 recorded views among 60 auxiliary ones get one step in 16, and the
model drifts toward corrected copies of its own early renders). With ``save_pictures`` the run
folder gets ``auxiliary_views.jpg``: reference | render | refined for a few auxiliary views
(refined pixels outside the refiner's mask are dimmed).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from protocol.camera import Camera, Pose
from reconstructor.data.views import View
from reconstructor.errors import ReconstructConfigError
from reconstructor.raster import RasterConfig
from reconstructor.refine.base import Refined, Refiner
from reconstructor.refine.checked import checked_refined, refine_request, unrecorded_view
from reconstructor.refine.eye_views import EyeViewConfig
from reconstructor.refine.guided import GuidedConfig
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import render

log = logging.getLogger(__name__)

FALLBACK_LOOK_AT_M = 2.0  # when the model renders (almost) nothing from an input camera
MIN_DEPTH_PIXELS = 0.01  # the fraction of confident pixels needed for a median depth
BOUNDS_MARGIN_M = 0.05  # auxiliary cameras keep this far from the room's walls, floor, ceiling
SHEET_ROWS = 4
SHEET_TILE_WIDTH_PX = 320


@dataclass(frozen=True, kw_only=True)
class AuxiliaryConfig:
    enabled: bool = True  # false: "EgoSurg without diffusion" (input views only)
    num_views: int = 15  # N per input camera (paper)
    radius_m: float = 0.4  # R (paper)
    min_radius_m: float = 0.1  # closer than this an auxiliary view is the input view again
    look_at_depth_m: float = 0.0  # 0: the input view's median rendered depth
    refiner: str = "guided"  # "guided", "difix", "none", or a plug-in
    refiner_weights: str = ""  # local weights path for a refiner that needs them
    aux_weight: float = 1.0  # loss weight of an auxiliary view relative to an input view
    # share of the refinement steps on the recorded views (0: drawn like any auxiliary view)
    # measured, near-field: 0.8 beat 0.5 at 500 + 1500 steps (29.1 vs 28.9 dB, session 10); with
    # the snapped room shell, 0.95 beat 0.8 (32.7 vs 32.2 dB; egocentric 20.65 vs 20.71);
    # EVALUATION.md
    input_share: float = 0.95
    seed: int = 0
    save_pictures: bool = True  # auxiliary_views.jpg in the run folder
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    # cameras where people's eyes will be, besides the shell (eye_views.py)
    eye: EyeViewConfig = field(default_factory=EyeViewConfig)

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ReconstructConfigError:
            return ReconstructConfigError(f"auxiliary.{name}={getattr(self, name)!r}: {why}")

        for name in ("enabled", "save_pictures"):
            if not isinstance(getattr(self, name), bool):
                raise bad(name, "must be true or false")
        for name in ("num_views", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise bad(name, "must be an integer")
        if self.num_views < 1:
            raise bad("num_views", "must be at least 1 (set enabled = false for none)")
        if self.seed < 0:
            raise bad("seed", "must be >= 0")
        for name in ("radius_m", "min_radius_m", "look_at_depth_m", "aux_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise bad(name, "must be a finite number")
        if not 0.0 < self.radius_m <= 5.0:
            raise bad("radius_m", "must be in (0, 5] metres")
        if not 0.0 <= self.min_radius_m <= self.radius_m:
            raise bad("min_radius_m", f"must be in [0, radius_m={self.radius_m!r}]")
        if self.look_at_depth_m < 0:
            raise bad("look_at_depth_m", "must be >= 0 (0: the median rendered depth)")
        if self.aux_weight < 0:
            raise bad("aux_weight", "must be >= 0")
        if isinstance(self.input_share, bool) or not 0.0 <= self.input_share < 1.0:
            raise bad("input_share", "must be in [0, 1)")
        if not isinstance(self.refiner, str) or not self.refiner:
            raise bad("refiner", "must name a refiner: guided, difix, none or a plug-in")
        if not isinstance(self.refiner_weights, str):
            raise bad("refiner_weights", "must be a path (a string)")

    def refinement_shares(self, with_eye_views: bool) -> tuple[float, float, float]:
        """The refinement steps' shares (``Trainer.run_mixed``) of the recorded views, the
        auxiliary views and the eye-height views (0 without them), with ``input_share`` > 0."""
        rest = 1.0 - (self.eye.share if with_eye_views else 0.0)
        return self.input_share * rest, (1.0 - self.input_share) * rest, 1.0 - rest


Bounds = tuple[np.ndarray, np.ndarray]  # (lo (3,), hi (3,)) in world metres; ±inf: unbounded


def sample_auxiliary_poses(
    camera: Camera,
    n: int,
    radius_m: float,
    rng: np.random.Generator,
    *,
    min_radius_m: float = 0.1,
    look_at_depth_m: float = FALLBACK_LOOK_AT_M,
    bounds_m: Bounds | None = None,
) -> list[Pose]:
    """``n`` world-to-camera poses around ``camera`` (module docstring, steps 2 and 3).

    With ``bounds_m``, centres closer than ``BOUNDS_MARGIN_M`` to a bound are redrawn; if
    ``50 n`` draws do not give ``n`` such centres, fewer poses are returned (with a warning).
    """
    if not 0.0 <= min_radius_m <= radius_m:
        raise ValueError(f"min_radius_m={min_radius_m} must be in [0, radius_m={radius_m}]")
    if look_at_depth_m <= radius_m:
        raise ValueError(
            f"look_at_depth_m={look_at_depth_m} must exceed radius_m={radius_m}: an auxiliary "
            "camera must not pass the point it looks at"
        )
    R = camera.pose.R
    centre = camera.pose.centre_m
    forward, up = R[2], -R[1]  # the camera's z and image-up (-y, OpenCV axes) in the world
    target = centre + look_at_depth_m * forward
    if bounds_m is not None:
        lo = np.asarray(bounds_m[0], dtype=np.float64) + BOUNDS_MARGIN_M
        hi = np.asarray(bounds_m[1], dtype=np.float64) - BOUNDS_MARGIN_M
    poses: list[Pose] = []
    r3_lo, r3_hi = min_radius_m**3, radius_m**3
    for _ in range(50 * n):
        if len(poses) == n:
            break
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        if d @ forward < 0:
            d = -d
        r = np.cbrt(r3_lo + rng.uniform() * (r3_hi - r3_lo))  # uniform in the shell's volume
        eye = centre + r * d
        if bounds_m is not None and not (np.all(eye >= lo) and np.all(eye <= hi)):
            continue
        poses.append(Pose.look_at(eye, target, up=up))
    if len(poses) < n:
        log.warning(
            "%s: only %d of %d auxiliary cameras fit inside the room's bounds",
            camera.name,
            len(poses),
            n,
        )
    return poses


def median_depth_m(depth_m: np.ndarray, alpha: np.ndarray) -> float | None:
    """Median depth where the render is confident (alpha > 0.5), or None if too few pixels are."""
    sure = (alpha > 0.5) & (depth_m > 0)
    if sure.mean() < MIN_DEPTH_PIXELS:
        return None
    return float(np.median(depth_m[sure]))


@dataclass
class _Seconds:
    """Where the time of making auxiliary views went (``make_auxiliary_views``' timings_s)."""

    render: float = 0.0
    refine: float = 0.0


def make_auxiliary_views(
    gaussians: Gaussians,
    train_views: Sequence[View],
    config: AuxiliaryConfig,
    raster: RasterConfig,
    refiner: Refiner,
    *,
    bounds_m: Bounds | None = None,
    sheet_path: Path | None = None,
    timings_s: dict[str, float] | None = None,
) -> list[View]:
    """Auxiliary training views, ``config.num_views`` per input view (module docstring).

    ``sheet_path``: write the contact sheet there. ``timings_s``: receives the seconds spent
    rendering (``render``) and refining (``refine``).
    """
    rng = np.random.default_rng(config.seed)
    out: list[View] = []
    sheet: list[tuple[np.ndarray, np.ndarray, Refined]] = []
    sheet_every = max(1, len(train_views) // SHEET_ROWS)
    seconds = _Seconds()
    t_start = time.perf_counter()
    for i, view in enumerate(train_views):
        t0 = time.perf_counter()
        ref_depth, look = _reference_depth(gaussians, view, config, raster)
        seconds.render += time.perf_counter() - t0
        poses = sample_auxiliary_poses(
            view.camera,
            config.num_views,
            config.radius_m,
            rng,
            min_radius_m=config.min_radius_m,
            look_at_depth_m=look,
            bounds_m=bounds_m,
        )
        reference = view.image.numpy()  # for the contact sheet
        for k, pose in enumerate(poses):
            aux, rendered, refined = _auxiliary_view(
                gaussians, view, k, pose, raster, refiner, ref_depth_m=ref_depth, seconds=seconds
            )
            out.append(aux)
            if k == 0 and i % sheet_every == 0 and len(sheet) < SHEET_ROWS:
                sheet.append((reference, rendered, refined))
        log.info(
            "auxiliary views %d/%d (%s): %d views, look-at depth %.2f m",
            i + 1,
            len(train_views),
            view.name,
            len(poses),
            look,
        )
    total = time.perf_counter() - t_start
    size = f"{train_views[0].width_px}x{train_views[0].height_px}" if train_views else "-"
    log.info(
        "made %d auxiliary views at %s in %.1f s (rendering %.1f s, refiner %s %.1f s)",
        len(out),
        size,
        total,
        seconds.render,
        refiner.describe(),
        seconds.refine,
    )
    if timings_s is not None:
        timings_s["render"] = seconds.render
        timings_s["refine"] = seconds.refine
    if sheet_path is not None and sheet:
        write_contact_sheet(sheet_path, sheet)
    return out


def _reference_depth(
    gaussians: Gaussians, view: View, config: AuxiliaryConfig, raster: RasterConfig
) -> tuple[np.ndarray, float]:
    """The model's depth (H, W) from the input camera, and the auxiliary cameras' look-at depth
    in metres (module docstring, step 1)."""
    with torch.no_grad():
        ref = render(gaussians, view, raster)
    ref_depth = ref.depth_m.numpy()
    look = config.look_at_depth_m or median_depth_m(ref_depth, ref.alpha.numpy())
    if look is None:
        log.warning(
            "%s: the model renders almost nothing here; auxiliary cameras look %.1f m ahead",
            view.name,
            FALLBACK_LOOK_AT_M,
        )
        look = FALLBACK_LOOK_AT_M
    return ref_depth, max(look, 2 * config.radius_m)


def _auxiliary_view(
    gaussians: Gaussians,
    view: View,
    k: int,
    pose: Pose,
    raster: RasterConfig,
    refiner: Refiner,
    *,
    ref_depth_m: np.ndarray,
    seconds: _Seconds,
) -> tuple[View, np.ndarray, Refined]:
    """Auxiliary view ``k`` of input ``view``, at ``pose`` (module docstring, step 4), with the
    render (H, W, 3) and the refiner's answer it came from. ``ref_depth_m``: the model's depth
    (H, W) seen from ``view``."""
    t0 = time.perf_counter()
    aux = unrecorded_view(view, f"aux:{view.name}:{k}", pose)
    with torch.no_grad():
        r = render(gaussians, aux, raster)
    rendered = r.image.clamp(0, 1).numpy()
    t1 = time.perf_counter()
    seconds.render += t1 - t0
    refined = refiner.refine(refine_request(r, rendered, aux, view, ref_depth_m))
    seconds.refine += time.perf_counter() - t1
    image, mask = checked_refined(refined, view, refiner)
    return dataclasses.replace(aux, image=image, mask=mask), rendered, refined


def write_contact_sheet(path: Path, rows: Sequence[tuple[np.ndarray, np.ndarray, Refined]]) -> None:
    """reference | render | refined, one row per auxiliary view, each tile labelled."""
    labels = ("reference (input view)", "render (auxiliary camera)", "refined (dim: unused)")
    lines = []
    for reference, rendered, refined in rows:
        dimmed = refined.image * np.where(np.asarray(refined.mask, bool), 1.0, 0.35)[..., None]
        tiles = []
        for label, img in zip(labels, (reference, rendered, dimmed), strict=True):
            h, w = img.shape[:2]
            size = (SHEET_TILE_WIDTH_PX, max(1, round(h * SHEET_TILE_WIDTH_PX / w)))
            tile = cv2.resize((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), size)
            tile = np.ascontiguousarray(tile[:, :, ::-1])
            for colour, thick in (((0, 0, 0), 2), ((255, 255, 255), 1)):
                cv2.putText(tile, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, thick)
            tiles.append(tile)
        lines.append(np.concatenate(tiles, axis=1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0))) for line in lines]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(lines, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 90])
