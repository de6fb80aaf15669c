"""Line of sight: how much of a target box a viewer could see, over a case, and from a moved
(counterfactual) position.

At each instant the viewer's eye comes from their trajectory. A camera at the eye, aimed at the
target's centre and just wide enough to hold it, renders the case's model (our rasterizer) with
its far plane just before the target: the opacity of what lies in front. Each sampled target
point (``protocol.formats.site.surface_points``: the faces that face the eye) is visible where that
opacity is under one half. Aiming at the target, not where the head points, asks "could they
see it by looking", the question of a review; ``in_view_fraction`` says whether the target was
in their field of view then.

Two choices make the answer agree with rays cast through the true scene (bench/bench_sightline.py,
docs/replay.md):
- the viewer's own head never blocks (they could turn it): Gaussians within
  ``head_clearance_m`` of the eye are left out, a sphere, as the truth's rays start that far
  out. The back of a head lies up to 0.25 m behind the eye; the egocentric renders' 0.2 m near
  plane cut through it, so a screen behind the viewer counted their own skull as the blocker.
- occluders count at their core (``occluder_scale``): a Gaussian's opacity reaches past the
  surface it stands for by about its own size, and along a grazing ray many such tails add up
  to an opaque fringe around every silhouette. Seen from 0.3-0.5 m (the viewer's shoulders, a
  neighbour's head), a 3 cm fringe is a sixth of a monitor. Shrinking the occluders' extent for
  this render pulls their silhouette back towards their centres; inside a surface the
  neighbours still overlap and stay opaque. Not too far: in a weakly trained model (opacity
  about 0.1, a surface opaque only where many Gaussians overlap) half size already thins
  people and walls into see-through. 0.7 improves both the true-surface models and a
  reconstructed case over full size; 0.5 is better on the first, worse than full size on the
  second (docs/replay.md has the numbers).
- ``conserve_opacity`` (off) fits the shrinking to each occluder's own opacity: a shrunk
  Gaussian covers k^2 of its area, so its opacity is raised by 1/k^2 (at most
  ``MAX_OCCLUDER_OPACITY``) and its integrated opacity stays the same. A translucent Gaussian
  keeps what it adds to its surface's inside and loses only its tails; an opaque one (0.9, a
  true surface's) cannot rise, so it just shrinks to its core. Measured on three seeds, it
  helps models of opaque surfaces (true surfaces at 0.5: 94-99 % against 91-94 % at 0.7) and
  not the 3-step cases, whose stray stereo points (opacity 0.1) it makes opaque enough to
  block; it stays off until a trained case says otherwise (docs/replay.md).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

import numpy as np
import torch

from protocol.camera import Camera, Intrinsics, Pose
from protocol.formats.site import SiteBox, surface_points
from reconstructor.errors import SightlineError
from reconstructor.raster import RasterConfig
from reconstructor.splats.gaussians import Gaussians

_DIRECTIONS = {
    "anterior": (1, 0, 0), "forward": (1, 0, 0), "front": (1, 0, 0),
    "posterior": (-1, 0, 0), "back": (-1, 0, 0), "backward": (-1, 0, 0),
    "left": (0, 1, 0), "right": (0, -1, 0), "up": (0, 0, 1), "down": (0, 0, -1),
}  # fmt: skip
DEPTH_SIZE_PX = 192  # the aimed depth camera: enough for a grid of 12 x 12 points per face
HEAD_CLEARANCE_M = 0.3  # past the back of the viewer's head (sim: up to 0.25 m behind the eye)
MAX_OCCLUDER_OPACITY = 0.99  # conserve_opacity raises a shrunk Gaussian's opacity to at most this


@dataclass(frozen=True)
class SightlineConfig:
    """How the occlusion test treats the model (module docstring says why)."""

    head_clearance_m: float = HEAD_CLEARANCE_M  # Gaussians nearer the eye than this are left out
    occluder_scale: float = 0.7  # occluders' extent in the occlusion render, x their own
    conserve_opacity: bool = False  # raise a shrunk occluder's opacity by 1 / occluder_scale^2
    visible_below_alpha: float = 0.5  # a point is visible where less opaque than this in front
    size_px: int = DEPTH_SIZE_PX

    def __post_init__(self) -> None:
        if not (self.head_clearance_m >= 0 and 0 < self.occluder_scale <= 1):
            raise SightlineError(
                f"SightlineConfig: head_clearance_m {self.head_clearance_m} must be >= 0 and "
                f"occluder_scale {self.occluder_scale} in (0, 1]"
            )
        if not 0 < self.visible_below_alpha <= 1 or self.size_px < 8:
            raise SightlineError("SightlineConfig: visible_below_alpha in (0, 1], size_px >= 8")


@dataclass(frozen=True)
class Offset:
    """A move in the viewer's own frame: ``distance_m`` along ``direction`` (forward, left, up;
    forward is where the viewer faces, projected on the floor)."""

    distance_m: float
    direction: tuple[float, float, float]
    text: str

    def world_shift_m(self, pose: Pose) -> np.ndarray:
        look = pose.R.T @ np.array([0.0, 0.0, 1.0])
        fwd = np.array([look[0], look[1], 0.0])
        if np.linalg.norm(fwd) < 1e-6:  # looking straight down: the image's up is forward
            fwd = pose.R.T @ np.array([0.0, -1.0, 0.0])
            fwd[2] = 0.0
        fwd /= np.linalg.norm(fwd)
        up = np.array([0.0, 0.0, 1.0])
        left = np.cross(up, fwd)
        d = np.asarray(self.direction, float)
        return self.distance_m * (d[0] * fwd + d[1] * left + d[2] * up)


def parse_offset(text: str) -> Offset:
    """``"1m left-posterior"``, ``"0.5 m right"``, ``"80cm forward-up"``."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(m|cm)\s+([a-z-]+)\s*", text.lower())
    words = m.group(3).split("-") if m else []
    if not m or not words or any(w not in _DIRECTIONS for w in words):
        raise SightlineError(
            f"--offset {text!r}: write a distance and directions in the viewer's frame, e.g. "
            f'"1m left-posterior" (directions: {", ".join(sorted(_DIRECTIONS))})'
        )
    d = np.sum([_DIRECTIONS[w] for w in words], axis=0).astype(float)
    if np.linalg.norm(d) < 1e-9:
        raise SightlineError(f"--offset {text!r}: the directions cancel out")
    dist = float(m.group(1)) * (0.01 if m.group(2) == "cm" else 1.0)
    unit = d / np.linalg.norm(d)
    return Offset(dist, (float(unit[0]), float(unit[1]), float(unit[2])), text.strip())


def aimed_camera(eye_m: np.ndarray, points_m: np.ndarray, size_px: int = DEPTH_SIZE_PX) -> Camera:
    """A square pinhole at the eye aimed at the points' centre, wide enough to hold them all."""
    centre = points_m.mean(axis=0)
    pose = Pose.look_at(eye_m, centre)
    cam = pose.transform(points_m)
    if np.any(cam[:, 2] <= 0.05):
        raise SightlineError("the eye is inside or right at the target box")
    half = np.max(np.abs(cam[:, :2] / cam[:, 2:3]))
    fov = math.degrees(2 * math.atan(half * 1.15 + 0.01))
    if fov >= 170:
        raise SightlineError("the target box surrounds the eye: move the viewer or the box")
    return Camera(name="aimed", intrinsics=Intrinsics.from_fov(size_px, size_px, fov), pose=pose)


def depth_tolerance_m(distance_m: np.ndarray) -> np.ndarray:
    """How far in front of a target point the rendered surface must be to count as blocking it:
    a reconstructed surface is a few centimetres thick and its depth grows less sure with
    distance (stereo depth error grows with its square; 3 % covers our rig to 4 m)."""
    return 0.05 + 0.03 * distance_m


def occluders(g: Gaussians, eye_m: np.ndarray, config: SightlineConfig) -> Gaussians:
    """The Gaussians that may block the view from ``eye_m``: those past the viewer's head, at
    their core size (``config.occluder_scale``), with their integrated opacity kept where
    ``config.conserve_opacity`` asks (module docstring)."""
    eye = torch.as_tensor(np.asarray(eye_m, np.float32))
    keep = torch.linalg.vector_norm(g.means_m - eye, dim=1) >= config.head_clearance_m
    k = config.occluder_scale
    scales = g.log_scales[keep] + math.log(k)
    logits = g.opacity_logits[keep]
    if config.conserve_opacity and k < 1:
        o = torch.sigmoid(logits)  # one already above the cap keeps its own
        logits = torch.logit(torch.maximum(o, torch.clamp(o / k**2, max=MAX_OCCLUDER_OPACITY)))
    return dataclasses.replace(
        g, means_m=g.means_m[keep], quats_wxyz=g.quats_wxyz[keep], log_scales=scales,
        opacity_logits=logits, sh_dc=g.sh_dc[keep], sh_rest=g.sh_rest[keep],
    )  # fmt: skip


def visible_fraction(
    g: Gaussians, eye_m: np.ndarray, box: SiteBox, raster: RasterConfig, per_face: int = 12,
    config: SightlineConfig | None = None,
) -> tuple[float, dict]:  # fmt: skip
    """(fraction visible, details: the aimed camera, its opacity and RGB, the points' pixels
    and flags). 0 when no counted face of the box faces the eye."""
    from reconstructor.replay.run import render_view  # one render path for replay and this

    cfg = config or SightlineConfig()
    eye = np.asarray(eye_m, float)
    pts = surface_points(box, eye, per_face)
    if len(pts) == 0:
        return 0.0, {"points": 0}
    camera = aimed_camera(eye, pts, cfg.size_px)
    z = camera.pose.transform(pts)[:, 2]
    # Only what lies clearly in front of the target can block it: render the opacity of that
    # alone (far plane just before the target). A point is blocked where it is more than half
    # opaque; a depth test on the blended depth would call a faint floater in front a wall.
    # The head clearance is a sphere (occluders()), so the near plane here only guards the
    # projection.
    z_front = float(z.min())
    near = min(raster.near_m, 0.05)
    far = max(near + 0.01, z_front - float(depth_tolerance_m(np.asarray(z_front))))
    front = dataclasses.replace(raster, near_m=near, far_m=far)
    rgb, _, alpha = render_view(occluders(g, eye, cfg), camera, front)
    px, _ = camera.project(pts)
    h, w = alpha.shape
    u = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    visible = alpha[v, u] < cfg.visible_below_alpha
    return float(visible.mean()), {
        "points": len(pts), "camera": camera, "rgb": rgb, "alpha": alpha,
        "pixels": np.stack([u, v], 1), "visible": visible,
    }  # fmt: skip


def in_view_fraction(camera: Camera, box: SiteBox) -> float:
    """The fraction of the box's points (all faces) inside ``camera``'s image, in front of it."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / 2
    pts = (corners * np.asarray(box.size_m)) @ box.rotation.T + np.asarray(box.centre_m)
    px, z = camera.project(pts)
    w, h = camera.intrinsics.width_px, camera.intrinsics.height_px
    inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    return float(inside.mean())
