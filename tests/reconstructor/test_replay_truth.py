"""Line of sight against the simulator's exact truth: the sightline depth test, run on Gaussians
sampled from the true surfaces the rig's eight sensors see, against rays cast through the true
scene (``sim.roles.true_visible_fraction``), for every person x three screens x two positions."""

from __future__ import annotations

import numpy as np
import pytest

from bench.bench_sightline import true_surface_gaussians
from protocol.formats.site import SiteBox
from reconstructor.raster import RasterConfig
from reconstructor.replay.path import CameraPath
from reconstructor.replay.sightline import HEAD_CLEARANCE_M, parse_offset, visible_fraction
from sim.roles import role_trajectories, site_boxes, true_visible_fraction
from sim.world import World

T_S = 2.0


@pytest.fixture(scope="module")
def scene():
    world = World.from_seed(3, phase="intraoperative")
    return world, true_surface_gaussians(world, T_S)


def test_visible_fractions_from_a_true_surface_model_agree_with_ray_cast_truth(scene):
    """A reviewer relies on the sightline answer matching what the viewer could see. Stated
    tolerance: over 6 viewers x 3 screens x 2 positions (36 cases), "at least half visible"
    agrees with the truth in at least 91 % (one miss more than measured) and the fraction's mean
    absolute error is at most 0.09. (Measured: 94 %, 0.056; over 20 timestamps in
    bench/bench_sightline.py, docs/replay.md. Occluders at full size: 89 %, 0.12.)"""
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
                truth = true_visible_fraction(world, T_S, eye, box, near_m=HEAD_CLEARANCE_M)
                errors.append(abs(ours - truth))
                agree.append((ours >= 0.5) == (truth >= 0.5))
    assert len(errors) == 36
    assert np.mean(agree) >= 0.91, f"binary agreement {np.mean(agree):.2f}"
    assert np.mean(errors) <= 0.09, f"mean absolute error {np.mean(errors):.3f}"


def test_a_screen_right_behind_a_viewer_is_not_hidden_by_their_own_head(scene):
    """ "Could they see it by turning": a screen 1.2 m straight behind a viewer, with nothing
    between, is fully visible, not blocked by the back of their own head (0.2-0.25 m behind the
    eye, which a 0.2 m near plane left in, in the truth and in the model alike)."""
    world, g = scene
    raster = RasterConfig(near_m=0.2)
    open_behind = 0
    for pose in world.head_poses(T_S).values():
        back = -pose.R[2]
        back[2] = 0.0
        back /= np.linalg.norm(back)
        box = SiteBox(name="behind", centre_m=tuple(pose.centre_m + 1.2 * back),  # type: ignore[arg-type]
                      size_m=(0.01, 0.4, 0.3), front_only=True,
                      yaw_deg=float(np.degrees(np.arctan2(-back[1], -back[0]))))  # fmt: skip
        if true_visible_fraction(world, T_S, pose.centre_m, box) < 1.0:
            continue  # someone or something else stands behind this viewer
        open_behind += 1
        assert visible_fraction(g, pose.centre_m, box, raster)[0] == 1.0
    assert open_behind >= 3, f"only {open_behind} viewers have open space behind them"


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
