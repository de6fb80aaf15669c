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


# A ZED X-like rational lens (OpenCV's CALIB_RATIONAL_MODEL order: k1 k2 p1 p2 k3 k4 k5 k6)
RATIONAL = (-0.05, 0.1, 1e-4, -1e-4, 0.01, 0.3, 0.05, 0.02)


def rational_intrinsics() -> Intrinsics:
    return Intrinsics(width_px=1920, height_px=1200, fx_px=740.0, fy_px=739.6, cx_px=961.2,
                      cy_px=598.4, dist=RATIONAL)  # fmt: skip


def test_the_rational_model_is_eight_terms_and_five_pad_to_it():
    intr = rational_intrinsics()
    assert intr.is_rational and intr.dist8 == RATIONAL and intr.dist_array.shape == (8,)
    five = Intrinsics(width_px=960, height_px=600, fx_px=480.0, fy_px=480.0, cx_px=479.5,
                      cy_px=299.5, dist=(0.1, 0.01, 0, 0, -0.002))  # fmt: skip
    assert not five.is_rational and five.dist8 == (0.1, 0.01, 0.0, 0.0, -0.002, 0.0, 0.0, 0.0)
    assert not intr.undistorted().has_distortion
    with pytest.raises(ValueError, match=r"5 terms .* or 8"):
        Intrinsics(width_px=10, height_px=10, fx_px=1.0, fy_px=1.0, cx_px=5.0, cy_px=5.0,
                   dist=(0.0,) * 6)  # fmt: skip


def test_undistorting_inverts_the_rational_projection_over_the_whole_image():
    """Every pixel of the image, corners included, goes back through OpenCV's rational model to
    the ray that projects onto it (what the sim's rays and calibration's detector rely on)."""
    import cv2

    from protocol.camera import undistort_to_normalized

    intr = rational_intrinsics()
    u, v = np.meshgrid(np.linspace(0, 1919, 25), np.linspace(0, 1199, 16))
    px = np.column_stack([u.ravel(), v.ravel()])
    xy = undistort_to_normalized(px, intr)
    rays = np.column_stack([xy, np.ones(len(xy))])
    back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), intr.K, intr.dist_array)
    np.testing.assert_allclose(back.reshape(-1, 2), px, atol=1e-6)
