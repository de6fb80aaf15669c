"""The depth-reprojection baseline draws every valid pixel of every depth map into the target
view, sized by its footprint, and leaves what no depth map saw as holes it counts."""

from __future__ import annotations

import numpy as np

from protocol.camera import Camera, Intrinsics, Pose
from reconstructor.depth.stereo import DepthMap
from reconstructor.evaluation.baselines import hole_fraction, reproject_depth_maps

INTR = Intrinsics(width_px=160, height_px=100, fx_px=120.0, fy_px=120.0, cx_px=79.5, cy_px=49.5)


def _depth_map(depth_m: np.ndarray, valid: np.ndarray, seed: int = 0) -> DepthMap:
    rgb = np.random.default_rng(seed).integers(0, 256, (*depth_m.shape, 3), dtype=np.uint8)
    d = np.where(valid, depth_m, np.nan).astype(np.float32)
    return DepthMap(
        depth_m=d, valid=valid, disparity_px=d.copy(), intrinsics=INTR,
        rect_from_left=np.eye(3), baseline_m=0.12, rgb=rgb,
    )  # fmt: skip


def _camera(centre_m) -> Camera:
    # looking along +z like the identity pose, from centre_m
    return Camera(
        name="t", intrinsics=INTR, pose=Pose(R=np.eye(3), t_m=-np.asarray(centre_m, float))
    )


def test_a_depth_map_seen_from_its_own_camera_comes_back_pixel_for_pixel() -> None:
    valid = np.ones((100, 160), bool)
    valid[40:60, 70:90] = False  # a hole in the stereo
    dm = _depth_map(np.full((100, 160), 2.0), valid)
    image, holes = reproject_depth_maps([(dm, _camera([0, 0, 0]).pose)], _camera([0, 0, 0]))
    assert np.array_equal(holes, ~valid)  # holes are where stereo had none, nowhere else
    assert np.allclose(image[valid], dm.rgb[valid] / 255.0, atol=1e-6)
    assert (image[~valid] == 0).all()  # holes stay black
    assert hole_fraction(holes) == (~valid).mean()
    assert hole_fraction(holes, valid) == 0.0


def test_moving_closer_to_a_surface_does_not_open_gaps_between_its_pixels() -> None:
    """Each pixel is drawn at its footprint at its depth: 0.5 m closer to a wall 2 m away, the
    pixels grow 1.33x and still cover the wall without holes."""
    dm = _depth_map(np.full((100, 160), 2.0), np.ones((100, 160), bool))
    _, holes = reproject_depth_maps([(dm, _camera([0, 0, 0]).pose)], _camera([0, 0, 0.5]))
    assert hole_fraction(holes[5:-5, 5:-5]) == 0.0


def test_what_no_depth_map_saw_is_a_hole() -> None:
    """A box 1.5 m away in front of a wall at 3 m: from 0.4 m to the side, the strip of wall the
    box hid from the depth map's camera is a hole, and the rest is not."""
    depth = np.full((100, 160), 3.0)
    depth[30:70, 60:100] = 1.5
    dm = _depth_map(depth, np.ones((100, 160), bool))
    _, holes = reproject_depth_maps([(dm, _camera([0, 0, 0]).pose)], _camera([0.4, 0, 0]))
    # the box moves left by f * 0.4 / 1.5 = 32 px, the wall behind it by 16 px: the 16 px right
    # of the box's new place were behind the box
    assert holes[35:65, 100 - 32 + 2 : 100 - 16 - 2].all()
    assert not holes[35:65, 10:40].any()  # wall seen by both
    assert 0.02 < hole_fraction(holes) < 0.3


def test_two_depth_maps_fill_each_others_holes() -> None:
    valid_a = np.ones((100, 160), bool)
    valid_a[:, :80] = False
    valid_b = ~valid_a
    wall = np.full((100, 160), 2.0)
    pose = _camera([0, 0, 0]).pose
    sources = [(_depth_map(wall, valid_a, 1), pose), (_depth_map(wall, valid_b, 2), pose)]
    _, holes = reproject_depth_maps(sources, _camera([0, 0, 0]))
    assert not holes.any()
