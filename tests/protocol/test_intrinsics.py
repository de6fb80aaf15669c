"""Pinhole intrinsics: a camera's model for an image a whole number of times smaller."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.camera import Camera, Intrinsics, Pose


def test_a_shrunk_camera_sees_each_point_where_the_full_one_does_scaled_about_pixel_corners():
    """A pixel covers [u - 0.5, u + 0.5] at either size, so a point at full-size pixel u lies at
    (u + 0.5) / f - 0.5 in an image f times smaller; the distortion is dropped (the smaller
    image is an ideal pinhole)."""
    full = Intrinsics(width_px=960, height_px=600, fx_px=480.0, fy_px=470.0, cx_px=471.3,
                      cy_px=305.8, dist=(0.1, 0, 0, 0, 0))  # fmt: skip
    pose = Pose.look_at(np.array([0.0, -2.0, 1.5]), np.array([0.0, 0.0, 1.0]))
    rng = np.random.default_rng(1)
    points = rng.uniform([-1, -0.5, 0.5], [1, 0.5, 1.5], (20, 3))
    big, _ = Camera(name="c", intrinsics=full.undistorted(), pose=pose).project(points)
    for factor in (1, 2, 4):
        small = full.shrunk(factor)
        assert (small.width_px, small.height_px) == (960 // factor, 600 // factor)
        assert not small.has_distortion
        uv, _ = Camera(name="c", intrinsics=small, pose=pose).project(points)
        np.testing.assert_allclose(uv, (big + 0.5) / factor - 0.5, atol=1e-9)
    with pytest.raises(ValueError, match="at least 1"):
        full.shrunk(0)
