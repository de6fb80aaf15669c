"""The simulated cameras are geometrically exact: what calibration and reconstruction will assume
about a ZED X holds in the sim's images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from protocol.camera import Camera, Pose, Resolution
from protocol.formats.zed_conf import ZedFactoryCalibration
from sim.render import ray_directions


def _rectify(st):
    size = (st.left.width_px, st.left.height_px)
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
        st.left.K,
        st.left.dist_array,
        st.right.K,
        st.right.dist_array,
        size,
        st.R_right_from_left,
        st.T_right_from_left_m.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0,
    )
    return R1, R2, P1, P2


def test_ray_directions_invert_the_lens_model(world):
    """Every pixel's ray projects back onto that pixel, corners of the wide lens included (this
    sensor has the rational model, k4..k6)."""
    intr = world.sensor(0, "left", "SVGA").intrinsics
    assert intr.is_rational
    dirs = ray_directions(intr)
    pick = [(0, 0), (0, intr.width_px - 1), (intr.height_px - 1, 0), (300, 480), (599, 959)]
    pts = np.array([dirs[v, u] for v, u in pick], np.float64)
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intr.K, intr.dist_array)
    np.testing.assert_allclose(px.reshape(-1, 2), [(u, v) for v, u in pick], atol=1e-3)


def test_one_sensor_renders_the_rational_model_its_factory_file_carries(world, tmp_path):
    """Unit 0's left sensor is on the 8-term rational model in every mode (the others keep five
    terms); its SN<serial>.conf carries k4..k6 and reads back to the lens the sim renders, which
    images the scene within about a pixel of a five-term ZED X lens."""
    from sim.rig import RATIONAL_FIT_MAX_R2

    unit = world.rig[0]
    cal = ZedFactoryCalibration.read(unit.factory.write(tmp_path))
    assert cal == unit.factory
    for res in Resolution:
        assert cal.left[res].is_rational and not cal.right[res].is_rational
    assert not any(u.factory.left[Resolution.HD1200].is_rational for u in world.rig[1:])
    k1, k2, _, _, k3, k4, k5, k6 = cal.left[Resolution.HD1200].dist
    r2 = np.linspace(0.0, RATIONAL_FIT_MAX_R2, 50)
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    # the five-term lens nearest to it is one the sim draws (k1 k2 k3 around -0.042 0.018 -0.004),
    # within a pixel (fx = 740 px) over the field; without its denominator it would be far off
    powers = np.column_stack([r2, r2**2, r2**3])
    five, *_ = np.linalg.lstsq(powers, radial - 1, rcond=None)
    assert np.abs(five - [-0.042, 0.018, -0.004]).max() < 0.0045
    assert np.abs(np.sqrt(r2) * (radial - 1 - powers @ five)).max() * 740 < 1.0
    assert np.abs(np.sqrt(r2) * (radial - 1 - powers @ [k1, k2, k3])).max() * 740 > 100


def test_known_point_lands_at_disparity_fB_over_Z_after_rectification(world, tmp_path):
    """Using only what the .conf file says: a point at depth Z has disparity f*B/Z, same row."""
    unit = world.rig[2]
    cal = ZedFactoryCalibration.read(unit.factory.write(tmp_path))
    st = cal.stereo("HD1200")
    R1, R2, P1, P2 = _rectify(st)
    f, B = P1[0, 0], -P2[0, 3] / P2[0, 0]
    assert B == pytest.approx(st.baseline_m, rel=1e-9)
    left, right = unit.sensor("left", "HD1200"), unit.sensor("right", "HD1200")
    rng = np.random.default_rng(0)
    for _ in range(20):
        # a point inside the view, 1.5 to 6 m along the rectified left camera's axis
        Z = rng.uniform(1.5, 6.0)
        p_rect = np.array([rng.uniform(-0.4, 0.4) * Z, rng.uniform(-0.3, 0.3) * Z, Z])
        p_world = left.pose.inverse().transform((R1.T @ p_rect)[None])[0]
        uv_l, _ = left.project(p_world[None])
        uv_r, _ = right.project(p_world[None])
        rl = cv2.undistortPoints(uv_l.reshape(1, 1, 2), st.left.K, st.left.dist_array, R=R1, P=P1)
        rr = cv2.undistortPoints(uv_r.reshape(1, 1, 2), st.right.K, st.right.dist_array, R=R2, P=P2)
        rl, rr = rl.reshape(2), rr.reshape(2)
        assert rl[1] == pytest.approx(rr[1], abs=0.01)
        assert rl[0] - rr[0] == pytest.approx(f * B / Z, abs=0.01)


def test_stereo_matching_on_rendered_images_recovers_true_disparity(world):
    """In the rendered images themselves: OpenCV's SGBM on the rectified pair finds the disparity
    f*B/Z that the true depth predicts, as it would on real footage of a textured room."""
    unit = world.rig[0]
    st = unit.factory.stereo("SVGA")
    left, right = world.render_stereo(unit.index, 3.0, "SVGA")
    R1, R2, P1, P2 = _rectify(st)
    size = (st.left.width_px, st.left.height_px)
    ml = cv2.initUndistortRectifyMap(st.left.K, st.left.dist_array, R1, P1, size, cv2.CV_32FC1)
    mr = cv2.initUndistortRectifyMap(st.right.K, st.right.dist_array, R2, P2, size, cv2.CV_32FC1)
    gl = cv2.cvtColor(cv2.remap(left.image_rgb, *ml, cv2.INTER_LINEAR), cv2.COLOR_RGB2GRAY)
    gr = cv2.cvtColor(cv2.remap(right.image_rgb, *mr, cv2.INTER_LINEAR), cv2.COLOR_RGB2GRAY)
    depth_l = cv2.remap(left.depth_m, *ml, cv2.INTER_NEAREST)
    f, B = P1[0, 0], -P2[0, 3] / P2[0, 0]
    h, w = gl.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    # depth along the rectified axis: rotate the left-camera ray into the rectified frame
    ray_rect = np.stack([(u - P1[0, 2]) / f, (v - P1[1, 2]) / f, np.ones_like(u, float)], -1)
    z_rect = depth_l / (ray_rect @ R1)[..., 2]
    truth = f * B / z_rect
    sgbm = cv2.StereoSGBM_create(
        0, 64, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY
    )
    disp = sgbm.compute(gl, gr).astype(np.float32) / 16.0
    valid = (disp > 0) & np.isfinite(truth)
    assert valid.mean() > 0.5
    err = disp[valid] - truth[valid]
    assert abs(np.median(err)) < 0.25
    assert np.mean(np.abs(err) < 1.0) > 0.6
    # the check can fail: against a wrong baseline (110 mm) the same disparities disagree
    wrong = f * 0.110 / z_rect
    assert np.mean(np.abs(disp[valid] - wrong[valid]) < 1.0) < np.mean(np.abs(err) < 1.0) - 0.15


def test_virtual_camera_at_the_left_sensor_sees_the_undistorted_left_image(world):
    unit = world.rig[1]
    t = 2.5
    sensor = world.render_sensor(unit.index, "left", t, Resolution.SVGA, noise=False)
    intr = sensor.camera.intrinsics
    undist = cv2.undistort(sensor.image_rgb, intr.K, intr.dist_array)
    virtual = Camera(name="at-left", intrinsics=intr.undistorted(), pose=sensor.camera.pose)
    view = world.render(virtual, t)
    inner = (slice(40, -40), slice(60, -60))  # undistort leaves empty borders

    def psnr(a, b):
        mse = np.mean((a[inner].astype(float) - b[inner].astype(float)) ** 2)
        return 10 * np.log10(255.0**2 / mse)

    same = psnr(undist, view.image_rgb)
    assert same > 30.0
    # the comparison can fail: 2 cm to the side is visibly a different view
    pose = sensor.camera.pose
    moved_pose = Pose(R=pose.R, t_m=pose.t_m - pose.R @ np.array([0.02, 0.0, 0.0]))
    moved = world.render(Camera(name="moved", intrinsics=virtual.intrinsics, pose=moved_pose), t)
    assert psnr(undist, moved.image_rgb) < same - 6.0
    # and the depth maps agree to a millimetre where both see a surface
    d_undist = cv2.remap(
        sensor.depth_m,
        *cv2.initUndistortRectifyMap(
            intr.K, intr.dist_array, None, intr.K, (intr.width_px, intr.height_px), cv2.CV_32FC1
        ),
        cv2.INTER_LINEAR,
    )
    diff = np.abs(d_undist[inner] - view.depth_m[inner])
    assert np.median(diff[np.isfinite(diff)]) < 0.001


@pytest.mark.parametrize("seed", range(0, 40, 3))
def test_every_camera_of_a_rig_could_hang_on_its_wall(seed):
    """Both sensors and the whole 188 mm ZED X housing (34 mm past each sensor) are inside the
    room, 2 cm from every wall: a camera the sim renders is one a clinical engineer could mount."""
    from sim.rig import build_rig
    from sim.room import RoomSpec

    room = RoomSpec()
    half = np.array([room.length_x_m / 2, room.width_y_m / 2])
    for unit in build_rig(seed, room):
        left = unit.sensor("left", Resolution.SVGA).pose.centre_m
        right = unit.sensor("right", Resolution.SVGA).pose.centre_m
        along = (right - left) / np.linalg.norm(right - left)
        for end in (left - 0.034 * along, right + 0.034 * along):
            gap_to_wall_m = np.min(half - np.abs(end[:2]))
            assert gap_to_wall_m >= 0.02, (seed, unit.serial, end, gap_to_wall_m)
            assert 0.02 <= end[2] <= room.height_z_m - 0.02
