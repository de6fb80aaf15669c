"""A small sim scene shared by the refinement tests: the rig's four left cameras at a few dozen
pixels, their ideal images, Gaussians seeded from the true depth (what a perfect stereo init
would give), and a perfect refiner."""

from __future__ import annotations

import numpy as np
import torch

from protocol.camera import Camera, Intrinsics
from reconstructor.data.views import View, view_from_image
from reconstructor.evaluation.metrics import psnr
from reconstructor.raster import RasterConfig
from reconstructor.refine.base import Refined, Refiner, RefineRequest
from reconstructor.splats.gaussians import Gaussians, init_from_points
from reconstructor.splats.train import render

T_S = 1.0
ROOM = (np.array([-3.5, -3.0, 0.0]), np.array([3.5, 3.0, 3.0]))  # the sim's 7 x 6 x 3 m room


def true_depth_scene(world, size: tuple[int, int]) -> tuple[list[View], Gaussians]:
    """The four left rig cameras at ``size`` (hfov 100 degrees) and Gaussians from the true depth
    of every second pixel."""
    intr = Intrinsics.from_fov(*size, 100.0)
    cams = [
        Camera(name=f"cam{i}", intrinsics=intr, pose=unit.left_pose)
        for i, unit in enumerate(world.rig)
    ]
    renders = [world.render(c, T_S) for c in cams]
    views = [view_from_image(c, r.image_rgb) for c, r in zip(cams, renders, strict=True)]
    pts, cols = [], []
    Kinv = np.linalg.inv(intr.K)
    for c, r in zip(cams, renders, strict=True):
        v, u = np.mgrid[0 : size[1] : 2, 0 : size[0] : 2]
        z = r.depth_m[v, u]
        hit = np.isfinite(z)
        rays = Kinv @ np.stack([u[hit], v[hit], np.ones(hit.sum())])
        pts.append(((rays * z[hit]).T - c.pose.t_m) @ c.pose.R)
        cols.append(r.image_rgb[v[hit], u[hit]] / 255.0)
    return views, init_from_points(np.concatenate(pts), np.concatenate(cols))


class TruthRefiner(Refiner):
    """Returns what the sim sees from the auxiliary camera: a perfect refiner."""

    name = "truth"

    def __init__(self, world) -> None:
        self.world = world
        self.requests: list[RefineRequest] = []

    def refine(self, request: RefineRequest) -> Refined:
        self.requests.append(request)
        img = self.world.render(request.camera, T_S).image_rgb
        return Refined(image=img.astype(np.float32) / 255, mask=np.ones(img.shape[:2], bool))


def mean_psnr(model: Gaussians, views: list[View], raster: RasterConfig) -> float:
    """The mean PSNR of the model's renders (clamped to [0, 1]) against ``views``' images."""
    with torch.no_grad():
        scores = [
            psnr(render(model, v, raster).image.clamp(0, 1).numpy(), v.image.numpy()) for v in views
        ]
    return float(np.mean(scores))
