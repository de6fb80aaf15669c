"""Line of sight: how much of a target box a viewer could see, over a case, and from a moved
(counterfactual) position.

At each instant the viewer's eye comes from their trajectory. A camera at the eye, aimed at the
target's centre and just wide enough to hold it, renders the case's model (our rasterizer, the
eye's near plane leaving out the viewer's own head) with its far plane just before the target:
the opacity of what lies in front. Each sampled target point (``protocol.site.surface_points``:
the faces that face the eye) is visible where that opacity is under one half. Aiming at the
target, not where the head points, asks "could they see it by looking", the question of a
review; ``in_view_fraction`` says whether the target was in their field of view then.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

import numpy as np

from protocol.camera import Camera, Intrinsics, Pose
from protocol.site import SiteBox, surface_points
from reconstructor.errors import ReconstructError
from reconstructor.raster import RasterConfig
from reconstructor.splats.gaussians import Gaussians

_DIRECTIONS = {
    "anterior": (1, 0, 0), "forward": (1, 0, 0), "front": (1, 0, 0),
    "posterior": (-1, 0, 0), "back": (-1, 0, 0), "backward": (-1, 0, 0),
    "left": (0, 1, 0), "right": (0, -1, 0), "up": (0, 0, 1), "down": (0, 0, -1),
}  # fmt: skip
DEPTH_SIZE_PX = 192  # the aimed depth camera: enough for a grid of 12 x 12 points per face


class SightlineError(ReconstructError, ValueError):
    pass


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


def visible_fraction(
    g: Gaussians, eye_m: np.ndarray, box: SiteBox, raster: RasterConfig, per_face: int = 12
) -> tuple[float, dict]:
    """(fraction visible, details: the aimed camera, its depth and RGB, the points' pixels and
    flags). 0 when no counted face of the box faces the eye."""
    from reconstructor.replay.run import render_view  # one render path for replay and this

    pts = surface_points(box, eye_m, per_face)
    if len(pts) == 0:
        return 0.0, {"points": 0}
    camera = aimed_camera(np.asarray(eye_m, float), pts)
    z = camera.pose.transform(pts)[:, 2]
    # Only what lies clearly in front of the target can block it: render the opacity of that
    # alone (far plane just before the target). A point is blocked where it is more than half
    # opaque; a depth test on the blended depth would call a faint floater in front a wall.
    z_front = float(z.min())
    far = max(raster.near_m + 0.01, z_front - float(depth_tolerance_m(np.asarray(z_front))))
    front = dataclasses.replace(raster, far_m=far)
    rgb, _, alpha = render_view(g, camera, front)
    px, _ = camera.project(pts)
    h, w = alpha.shape
    u = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    visible = alpha[v, u] < 0.5
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
