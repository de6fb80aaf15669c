"""Line of sight against the simulator's exact truth: the sightline depth test, run on Gaussians
sampled from the true surfaces the rig's eight sensors see, against rays cast through the true
scene (``sim.roles.true_visible_fraction``), for every person x three screens x two positions."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from protocol.site import SiteBox
from reconstructor.raster import RasterConfig
from reconstructor.replay.path import CameraPath
from reconstructor.replay.sightline import parse_offset, visible_fraction
from reconstructor.splats.gaussians import GaussianInitConfig, init_from_points
from sim.roles import role_trajectories, site_boxes, true_visible_fraction
from sim.world import World

T_S = 2.0


def _true_surface_gaussians(world: World, t_s: float, shrink: int = 4):
    """Gaussians at the true surface points each sensor sees (a quarter-size true depth map),
    coloured as seen: a model whose geometry is exact up to its Gaussians' size."""
    points, colours = [], []
    for unit in world.rig:
        for side in ("left", "right"):
            cam = unit.sensor(side, "SVGA")
            k = cam.intrinsics.undistorted()
            small = replace(
                k, width_px=k.width_px // shrink, height_px=k.height_px // shrink,
                fx_px=k.fx_px / shrink, fy_px=k.fy_px / shrink,
                cx_px=(k.cx_px + 0.5) / shrink - 0.5, cy_px=(k.cy_px + 0.5) / shrink - 0.5,
            )  # fmt: skip
            r = world.render(world.virtual_camera(cam.pose, small, name="truth"), t_s)
            v, u = np.nonzero(np.isfinite(r.depth_m))
            z = r.depth_m[v, u]
            xyz = np.stack([(u - small.cx_px) / small.fx_px * z,
                            (v - small.cy_px) / small.fy_px * z, z], 1)  # fmt: skip
            points.append((xyz - cam.pose.t_m) @ cam.pose.R)
            colours.append(r.image_rgb[v, u] / 255.0)
    return init_from_points(
        np.concatenate(points), np.concatenate(colours), GaussianInitConfig(opacity=0.9)
    )


@pytest.fixture(scope="module")
def scene():
    world = World.from_seed(3, phase="intraoperative")
    return world, _true_surface_gaussians(world, T_S)


def test_visible_fractions_from_a_true_surface_model_agree_with_ray_cast_truth(scene):
    """Stated tolerance: over 6 viewers x 3 screens x 2 positions (36 cases), "at least half
    visible" agrees with the truth in at least 80 % and the mean absolute error of the fraction
    is at most 0.20. (Measured: 86 %, 0.14; the misses are Gaussians seen from 0.2-0.5 m, the
    viewer's own shoulders and neighbours, which are fatter than the true surface.)"""
    world, g = scene
    raster = RasterConfig(near_m=0.2)
    offset = parse_offset("1m left-posterior")
    boxes: list[SiteBox] = site_boxes(world)
    assert len(boxes) == 3
    errors, agree = [], []
    for trajectory in role_trajectories(world, np.array([T_S])):
        pose = CameraPath(trajectory).pose(T_S)
        for box in boxes:
            for shift in (np.zeros(3), offset.world_shift_m(pose)):
                eye = pose.centre_m + shift
                ours, _ = visible_fraction(g, eye, box, raster)
                truth = true_visible_fraction(world, T_S, eye, box)
                errors.append(abs(ours - truth))
                agree.append((ours >= 0.5) == (truth >= 0.5))
    assert len(errors) == 36
    assert np.mean(agree) >= 0.80, f"binary agreement {np.mean(agree):.2f}"
    assert np.mean(errors) <= 0.20, f"mean absolute error {np.mean(errors):.3f}"


def test_a_screen_seen_from_behind_is_not_visible_and_an_open_view_is(scene):
    world, g = scene
    box = next(b for b in site_boxes(world) if b.name == "monitor-a")
    raster = RasterConfig(near_m=0.2)
    front = np.asarray(box.centre_m) + box.rotation @ np.array([1.0, 0.0, 0.0])
    behind = np.asarray(box.centre_m) - box.rotation @ np.array([0.5, 0.0, 0.0])
    assert true_visible_fraction(world, T_S, front, box) == 1.0
    assert visible_fraction(g, front, box, raster)[0] == 1.0
    assert visible_fraction(g, behind, box, raster)[0] == 0.0
    assert true_visible_fraction(world, T_S, behind, box) == 0.0
