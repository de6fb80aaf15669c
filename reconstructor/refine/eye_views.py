"""Auxiliary views where people's eyes will be.

The paper's auxiliary cameras (``auxiliary.py``) stay within 0.4 m of each wall camera; the
people whose views a team replays stand 1.7-3.0 m from the nearest one, so nothing trains the
model to look right from there. ``eye`` views add cameras inside the room:

1. eye positions are drawn uniformly over the floor (the room's box less ``wall_margin_m``, or
   when the box is unknown the cameras' own footprint) at a standing eye height, or with
   ``seated_share`` at a seated one; a position closer than ``clearance_m`` to any Gaussian's
   centre is inside a person or a machine and is drawn again;
2. each looks at a Gaussian at least ``min_opacity`` opaque (content, not a faded floater)
   between ``look_min_m`` and ``look_max_m`` away, below the eye (what people look at),
   image-up along the world's +z (the floor frame);
3. the model is rendered there, and the refiner is handed every recorded view that sees the
   point looked at, in order of how close its viewing direction is to the eye's (at most
   ``references``): each fills the pixels the ones before it left unsupervised, so content
   that one camera sees and another does not still gets a reference.

The views keep the recorded views' intrinsics and size. They train in the refinement stage as a
group of their own, with ``share`` of its steps (``pipeline.py``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from protocol.camera import Pose
from reconstructor.data.views import View
from reconstructor.errors import ReconstructConfigError
from reconstructor.raster import RasterConfig
from reconstructor.refine.base import Refiner
from reconstructor.refine.checked import checked_refined, refine_request, unrecorded_view
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import render

log = logging.getLogger(__name__)

DRAWS_PER_VIEW = 200  # tries per eye view before giving up (a room full of content)


@dataclass(frozen=True, kw_only=True)
class EyeViewConfig:
    num_views: int = 0  # 0: the paper's shell around each camera only
    standing_min_m: float = 1.5  # eye height above the floor, standing
    standing_max_m: float = 1.8
    seated_min_m: float = 1.1  # and seated (anaesthetist, perfusionist)
    seated_max_m: float = 1.3
    seated_share: float = 0.25
    wall_margin_m: float = 0.3  # people stand at least this far from the room's walls
    clearance_m: float = 0.3  # and this far from any content (else the eye is inside it)
    min_opacity: float = 0.1  # what eyes look at: Gaussians at least this opaque (3DGS's init)
    look_min_m: float = 0.8  # distance to the point looked at
    look_max_m: float = 3.5
    references: int = 4  # recorded views warped into each eye view, nearest direction first
    share: float = 0.2  # share of the refinement steps on eye views
    seed: int = 1

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ReconstructConfigError:
            return ReconstructConfigError(f"auxiliary.eye.{name}={getattr(self, name)!r}: {why}")

        for name in ("num_views", "references", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise bad(name, "must be an integer >= 0")
        if self.references < 1:
            raise bad("references", "must be at least 1")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.type == "float" and (
                isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)
            ):
                raise bad(f.name, "must be a finite number")
        if not 0 < self.seated_min_m <= self.seated_max_m:
            raise bad("seated_min_m", f"must be in (0, seated_max_m={self.seated_max_m}]")
        if not 0 < self.standing_min_m <= self.standing_max_m:
            raise bad("standing_min_m", f"must be in (0, standing_max_m={self.standing_max_m}]")
        if not 0 < self.look_min_m < self.look_max_m:
            raise bad("look_min_m", f"must be in (0, look_max_m={self.look_max_m})")
        for name in ("seated_share", "min_opacity"):
            if not 0 <= getattr(self, name) <= 1:
                raise bad(name, "must be in [0, 1]")
        if not 0 <= self.share < 1:
            raise bad("share", "must be in [0, 1)")
        if self.wall_margin_m < 0 or self.clearance_m < 0:
            raise bad("wall_margin_m", "the margins must be >= 0 metres")


@dataclass(frozen=True)
class EyePose:
    pose: Pose  # world-to-camera
    eye_m: np.ndarray  # (3,)
    target_m: np.ndarray  # (3,)


def floor_area(
    bounds_m: tuple[np.ndarray, np.ndarray] | None, camera_centres_m: np.ndarray, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(lo (2,), hi (2,)): where on the floor people may stand; the room's box in x and y less
    ``margin_m`` when it is known, else the rectangle of the cameras' centres."""
    lo = camera_centres_m[:, :2].min(axis=0)
    hi = camera_centres_m[:, :2].max(axis=0)
    if bounds_m is not None:
        blo, bhi = np.asarray(bounds_m[0][:2], float), np.asarray(bounds_m[1][:2], float)
        lo = np.where(np.isfinite(blo), blo + margin_m, lo)
        hi = np.where(np.isfinite(bhi), bhi - margin_m, hi)
    if np.any(hi <= lo):
        raise ReconstructConfigError(
            f"eye views: the floor area {lo.round(2).tolist()} - {hi.round(2).tolist()} m is "
            "empty; check room_bounds_m or set auxiliary.eye.num_views = 0"
        )
    return lo, hi


def sample_eye_poses(
    content_m: np.ndarray,
    targets_m: np.ndarray,
    area: tuple[np.ndarray, np.ndarray],
    floor_z_m: float,
    cfg: EyeViewConfig,
    rng: np.random.Generator,
) -> list[EyePose]:
    """Up to ``cfg.num_views`` eye cameras (module docstring, steps 1-2): clear of ``content_m``,
    each looking at one of ``targets_m``; fewer, with a warning, when the content leaves no room."""
    from scipy.spatial import cKDTree

    if cfg.num_views == 0:
        return []
    if len(content_m) == 0 or len(targets_m) == 0:
        log.warning("eye views: the model has no opaque content to look at; none made")
        return []
    # the balanced build crashes on flat content (a floor of equal z)
    tree = cKDTree(content_m, balanced_tree=False)
    targets = cKDTree(targets_m, balanced_tree=False)
    lo, hi = area
    out: list[EyePose] = []
    for _ in range(DRAWS_PER_VIEW * cfg.num_views):
        if len(out) == cfg.num_views:
            break
        seated = rng.uniform() < cfg.seated_share
        z0, z1 = (
            (cfg.seated_min_m, cfg.seated_max_m)
            if seated
            else (cfg.standing_min_m, cfg.standing_max_m)
        )
        eye = np.array([*rng.uniform(lo, hi), floor_z_m + rng.uniform(z0, z1)])
        if cfg.clearance_m > 0 and tree.query(eye)[0] < cfg.clearance_m:
            continue
        near = targets.query_ball_point(eye, cfg.look_max_m)
        if not near:
            continue
        pts = targets_m[near]
        d = np.linalg.norm(pts - eye, axis=1)
        ok = (d >= cfg.look_min_m) & (pts[:, 2] < eye[2])
        if not ok.any():
            continue
        target = pts[rng.choice(np.flatnonzero(ok))]
        out.append(EyePose(Pose.look_at(eye, target), eye, target))
    if len(out) < cfg.num_views:
        log.warning("eye views: only %d of %d positions found room", len(out), cfg.num_views)
    return out


def reference_order(eye: EyePose, views: Sequence[View]) -> list[int]:
    """Indices of the views that see ``eye.target_m`` (in front, inside the image), the one whose
    viewing direction is closest to the eye's first."""
    want = eye.target_m - eye.eye_m
    want = want / np.linalg.norm(want)
    scored = []
    for i, v in enumerate(views):
        cam = v.camera
        p = cam.pose.R @ eye.target_m + cam.pose.t_m
        if p[2] <= 0:
            continue
        k = cam.intrinsics
        u, w = k.fx_px * p[0] / p[2] + k.cx_px, k.fy_px * p[1] / p[2] + k.cy_px
        if not (0 <= u < k.width_px and 0 <= w < k.height_px):
            continue
        seen = eye.target_m - cam.pose.centre_m
        scored.append((-float(want @ (seen / np.linalg.norm(seen))), i))
    return [i for _, i in sorted(scored)]


def make_eye_views(
    gaussians: Gaussians,
    train_views: Sequence[View],
    cfg: EyeViewConfig,
    raster: RasterConfig,
    refiner: Refiner,
    *,
    bounds_m: tuple[np.ndarray, np.ndarray] | None,
) -> list[View]:
    """The eye views (module docstring), refined against the recorded views."""

    if cfg.num_views == 0 or not train_views:
        return []
    opacity = torch.sigmoid(gaussians.opacity_logits.detach()).cpu().numpy()
    content = gaussians.means_m.detach().cpu().numpy()
    centres = np.stack([v.camera.pose.centre_m for v in train_views])
    floor_z = 0.0
    if bounds_m is not None and np.isfinite(bounds_m[0][2]):
        floor_z = float(bounds_m[0][2])
    area = floor_area(bounds_m, centres, cfg.wall_margin_m)
    targets = content[opacity >= cfg.min_opacity]
    poses = sample_eye_poses(content, targets, area, floor_z, cfg, np.random.default_rng(cfg.seed))
    if not poses:
        return []
    with torch.no_grad():  # each recorded view's rendered depth: the refiner's occlusion test
        reference_depths_m = [render(gaussians, v, raster).depth_m.numpy() for v in train_views]
    base = train_views[0]
    out: list[View] = []
    for k, eye in enumerate(poses):
        aux = unrecorded_view(base, f"eye:{k}", eye.pose)
        with torch.no_grad():
            r = render(gaussians, aux, raster)
        rendered = r.image.clamp(0, 1).numpy()
        image = torch.from_numpy(rendered.astype(np.float32))
        mask = torch.zeros(aux.height_px, aux.width_px)
        for j in reference_order(eye, train_views)[: cfg.references]:
            request = refine_request(r, rendered, aux, train_views[j], reference_depths_m[j])
            refined = refiner.refine(request)
            img, m = checked_refined(refined, aux, refiner)
            new = (m > 0.5) & (mask < 0.5)
            image[new] = img[new]
            mask[new] = 1.0
        if float(mask.mean()) == 0.0:
            continue  # no recorded view supervises any of it
        out.append(dataclasses.replace(aux, image=image, mask=mask))
    log.info(
        "eye views: %d of %d drawn positions supervised (floor %s - %s m)",
        len(out),
        len(poses),
        area[0].round(2).tolist(),
        area[1].round(2).tolist(),
    )
    return out
