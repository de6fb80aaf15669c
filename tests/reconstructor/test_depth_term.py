"""The depth term (reconstructor/splats/depth_term.py, reconstructor/depth/reproject.py's
depth_targets): the rendered depth is the surface's, the term pulls a Gaussian along its ray
toward the stereo depth, a depth map drawn into its own view gives back its depths, and training
with the term keeps Gaussians on the true surfaces of the sim's room where the images alone let
them drift."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from protocol.camera import Camera, Intrinsics, Pose
from reconstructor.data.views import view_from_image
from reconstructor.depth.reproject import depth_targets
from reconstructor.depth.stereo import DepthMap
from reconstructor.errors import ReconstructConfigError
from reconstructor.raster import RasterConfig, rasterize
from reconstructor.splats.depth_term import depth_loss, rendered_depth
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import TrainConfig, Trainer, scene_extent_m
from tests.reconstructor.small_scene import T_S, true_depth_scene

INTR = Intrinsics.from_fov(64, 40, 70.0)
LOOK_Z = Pose(R=np.eye(3), t_m=np.zeros(3))  # world = camera: looking down +z


def plane(z_m: float, n: int = 12, opacity: float = 0.99) -> Gaussians:
    """An opaque fronto-parallel wall of small Gaussians at depth ``z_m``, wider than the view."""
    xs = np.linspace(-1.2, 1.2, n) * z_m
    ys = np.linspace(-0.8, 0.8, n) * z_m
    x, y = np.meshgrid(xs, ys)
    means = np.stack([x.ravel(), y.ravel(), np.full(x.size, z_m)], axis=1)
    spacing = xs[1] - xs[0]
    m = len(means)
    logit = float(np.log(opacity / (1 - opacity)))
    return Gaussians(
        means_m=torch.tensor(means, dtype=torch.float32),
        quats_wxyz=torch.tensor([[1.0, 0, 0, 0]]).repeat(m, 1),
        log_scales=torch.full((m, 3), float(np.log(spacing))),
        opacity_logits=torch.full((m,), logit),
        sh_dc=torch.zeros(m, 3),
        sh_rest=torch.zeros(m, 0, 3),
    )


def _view(image=None):
    cam = Camera(name="cam", intrinsics=INTR, pose=LOOK_Z)
    img = np.full((INTR.height_px, INTR.width_px, 3), 128, np.uint8) if image is None else image
    return view_from_image(cam, img)


def test_the_rendered_depth_of_an_opaque_wall_is_its_distance_and_the_rasterizers_own():
    view = _view()
    g = plane(2.5)
    raster = RasterConfig()
    d, alpha = rendered_depth(g, view.viewmat, view.K, view.width_px, view.height_px, raster)
    covered = alpha > 0.98
    assert covered.float().mean() > 0.9
    assert torch.allclose(d[covered] / alpha[covered], torch.tensor(2.5), atol=0.01)
    # the same quantity as the rasterizer's non-differentiable depth output (D / alpha)
    out = rasterize(g.means_m, g.quats_wxyz, g.log_scales, g.opacity_logits, g.colors(),
                    view.viewmat, view.K, view.width_px, view.height_px, torch.zeros(3),
                    raster)  # fmt: skip
    assert torch.allclose(d[covered], (out.depth_m * out.alpha)[covered], rtol=1e-4)


@pytest.mark.parametrize("min_alpha", [0.0, 0.5])
@pytest.mark.parametrize(("wall_m", "target_m"), [(2.5, 2.0), (2.0, 2.5)])
def test_the_term_pulls_the_wall_along_the_ray_toward_the_stereo_depth(wall_m, target_m, min_alpha):
    view = _view()
    g = plane(wall_m)
    g.means_m.requires_grad_(True)
    target = torch.full((view.height_px, view.width_px), target_m)
    target[:5] = float("nan")  # no stereo answer there: no pull
    d, alpha = rendered_depth(g, view.viewmat, view.K, view.width_px, view.height_px,
                              RasterConfig())  # fmt: skip
    depth_loss(d, alpha, target, min_alpha).backward()
    dz = g.means_m.grad[:, 2]
    # a gradient step (-grad) moves the wall toward the target depth
    assert float((-dz).sum()) * np.sign(target_m - wall_m) > 0
    assert float(depth_loss(d.detach(), alpha.detach(), torch.full_like(target, np.nan))) == 0.0


def test_a_depth_map_drawn_into_its_own_view_gives_back_its_depths():
    h, w = INTR.height_px, INTR.width_px
    v, u = np.mgrid[0:h, 0:w]
    depth = (2.0 + 0.01 * u + 0.02 * v).astype(np.float32)  # a tilted wall
    valid = np.ones((h, w), bool)
    valid[:, :8] = False  # stereo's blind strip
    dm = DepthMap(
        depth_m=np.where(valid, depth, np.nan).astype(np.float32), valid=valid,
        disparity_px=np.ones((h, w), np.float32), intrinsics=INTR, rect_from_left=np.eye(3),
        baseline_m=0.12, rgb=np.zeros((h, w, 3), np.uint8),
    )  # fmt: skip
    view = _view()
    other = dataclasses.replace(view, name="elsewhere")
    targets = depth_targets([view, other], {"cam": (dm, LOOK_Z)})
    assert set(targets) == {"cam"}  # a view without its pair's map gets no target
    t = targets["cam"]
    assert np.isnan(t[:, :8]).all()
    np.testing.assert_allclose(t[:, 8:], depth[:, 8:], rtol=1e-5)


def test_the_depth_settings_are_checked():
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ReconstructConfigError, match="depth_weight"):
            TrainConfig(depth_weight=bad)
    for bad in (-0.1, 1.0):
        with pytest.raises(ReconstructConfigError, match="depth_min_alpha"):
            TrainConfig(depth_min_alpha=bad)


SIZE = (48, 30)


@pytest.fixture(scope="module")
def scene(world):
    return true_depth_scene(world, SIZE)


def _true_depth(world, view) -> np.ndarray:
    cam = Camera(name=view.name, intrinsics=view.intrinsics, pose=view.pose)
    z = world.render(cam, T_S).depth_m.astype(np.float32)
    return np.where(np.isfinite(z), z, np.nan)


def test_training_with_the_term_keeps_the_gaussians_on_the_surfaces_stereo_saw(scene, world):
    """Gaussians seeded on the true surfaces, then pushed 10 cm along random directions (a
    noisy stereo init); 60 steps with and without the term, the true depth as its target.
    With it, the rendered depth from every input view ends nearer the truth."""
    views, seeded = scene
    truth = {v.name: _true_depth(world, v) for v in views}
    rng = np.random.default_rng(0)
    push = rng.normal(size=(seeded.num, 3))
    push *= 0.10 / np.linalg.norm(push, axis=1, keepdims=True)
    raster = RasterConfig()

    def depth_error(weight: float) -> float:
        g = seeded.detach_clone()
        with torch.no_grad():
            g.means_m += torch.as_tensor(push, dtype=torch.float32)
        cfg = TrainConfig(warmup_steps=60, refine_steps=0, depth_weight=weight,
                          random_background=False)  # fmt: skip
        trainer = Trainer(g, cfg, raster, scene_extent_m(views))
        trainer.set_depth_targets(truth)
        trainer.run(views, 60)
        errors = []
        with torch.no_grad():
            for v in views:
                d, a = rendered_depth(g, v.viewmat, v.K, v.width_px, v.height_px, raster)
                t = torch.from_numpy(truth[v.name])
                ok = torch.isfinite(t) & (a > 0.5)
                errors.append(((d[ok] / a[ok] - t[ok]).abs() / t[ok]).mean())
        return float(torch.stack(errors).mean())

    without, with_term = depth_error(0.0), depth_error(1.0)
    print(f"relative depth error: {without:.4f} without the term, {with_term:.4f} with it")
    assert with_term < 0.8 * without, (with_term, without)
