"""The rig solve against the simulator's truth.

Observations are synthesised without rendering: the true sphere centres of a wand session are
projected through each true sensor, with detection noise, gross outliers and occlusion. The sim's
world frame is not the solver's, so poses are compared camera-to-camera (relative to the
reference camera), and the floor frame by its normal and the cameras' heights.
"""

from __future__ import annotations

import dataclasses
import re
import time

import cv2
import numpy as np
import pytest

from calibration.errors import SolveError
from calibration.observations import WandObservations
from calibration.solve import bundle, linear
from calibration.solve.config import SolveConfig
from calibration.solve.solver import solve, thin_sets
from protocol.camera import Intrinsics, Resolution
from protocol.errors import ConfigError
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.wand import WandSpec
from sim.timing import SIM_EPOCH_UNIX_NS

RES = Resolution.HD1200


def synthesise(
    world,
    times_s: np.ndarray,
    *,
    centres: np.ndarray | None = None,
    noise_px: float = 0.07,
    outlier_fraction: float = 0.02,
    drop_fraction: float = 0.1,
    seed: int = 0,
    wand: WandSpec | None = None,
) -> tuple[WandObservations, np.ndarray]:
    """Observations of the true wand at ``times_s`` (or of the given (N, 3, 3) sphere
    ``centres``) and the (N, S, 3) mask of injected outliers."""
    rng = np.random.default_rng(seed)
    if centres is None:
        centres = np.stack([world.wand_centres(t) for t in times_s])
    sensors = [u.sensor(side, RES) for u in world.rig for side in ("left", "right")]
    n, s = len(times_s), len(sensors)
    points = np.full((n, s, 3, 2), np.nan)
    for i, cam in enumerate(sensors):
        px, z = cam.project(centres.reshape(-1, 3))
        px, z = px.reshape(n, 3, 2), z.reshape(n, 3)
        w, h = cam.intrinsics.width_px, cam.intrinsics.height_px
        inside = (z > 0.1) & (px >= 0).all(axis=2) & (px[..., 0] <= w - 1) & (px[..., 1] <= h - 1)
        noisy = px + rng.normal(0.0, noise_px, px.shape)
        points[:, i][inside] = noisy[inside]
    seen = np.isfinite(points).all(axis=3)
    outlier = seen & (rng.random(seen.shape) < outlier_fraction)
    angle = rng.uniform(0, 2 * np.pi, outlier.sum())
    size = rng.uniform(5.0, 30.0, outlier.sum())
    points[outlier] += np.c_[np.cos(angle), np.sin(angle)] * size[:, None]
    dropped = rng.random((n, s)) < drop_fraction  # occlusion: a sensor misses a whole set
    points[dropped] = np.nan
    outlier[dropped] = False
    obs = WandObservations(
        wand=wand or world.config.wand,
        camera_serials=tuple(u.serial for u in world.rig),
        stereo={u.serial: u.factory.stereo(RES) for u in world.rig},
        set_unix_ns=SIM_EPOCH_UNIX_NS + np.round(np.asarray(times_s) * 1e9).astype(np.int64),
        points_px=points,
    )
    return obs, outlier


def relative_errors(world, cal: RigCalibration, ref: int) -> dict[int, tuple[float, float]]:
    """Per camera: (rotation error deg, translation error mm) of its pose relative to the
    reference camera, solved vs true."""
    truth = {u.serial: u.left_pose for u in world.rig}
    ref_est = cal.sensor(ref, "left").pose.inverse()
    out = {}
    for sn, true_pose in truth.items():
        est = cal.sensor(sn, "left").pose.compose(ref_est)
        tru = true_pose.compose(truth[ref].inverse())
        cos = (np.trace(est.R @ tru.R.T) - 1) / 2
        out[sn] = (
            float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
            1000 * float(np.linalg.norm(est.t_m - tru.t_m)),
        )
    return out


def with_points(obs: WandObservations, points: np.ndarray, **changes) -> WandObservations:
    return dataclasses.replace(obs, points_px=points, **changes)


@pytest.fixture(scope="module")
def session(wand_world):
    """90 s of waving at 10 Hz, the first 2 s with the wand on the floor."""
    obs, outliers = synthesise(wand_world, np.arange(0.0, 90.0, 0.1))
    return obs, outliers, solve(obs)


# ---- the numeric core against slow twins ----------------------------------------------------


@pytest.mark.parametrize(
    "dist",
    [
        (-0.043, 0.019, 1.5e-4, -1.2e-4, -0.0041),  # five-term Brown-Conrady
        (-0.05, 0.1, 1.5e-4, -1.2e-4, 0.01, 0.3, 0.05, 0.02),  # eight-term rational (ZED X)
    ],
    ids=["five-term", "rational"],
)
def test_projection_and_its_jacobian_match_opencv(dist):
    intr = Intrinsics(
        width_px=1920,
        height_px=1200,
        fx_px=741.0,
        fy_px=740.2,
        cx_px=955.0,
        cy_px=603.0,
        dist=dist,
    )
    rng = np.random.default_rng(1)
    X = rng.uniform([-2, -1.5, 1.0], [2, 1.5, 5.0], size=(200, 3))
    table = np.tile([741.0, 740.2, 955.0, 603.0, *intr.dist8], (len(X), 1))
    px, J = bundle.project(X, table)
    assert J is not None
    ref, cvJ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), intr.K, intr.dist_array)
    np.testing.assert_allclose(px, ref.reshape(-1, 2), atol=1e-9)
    # with a zero pose, d(pixel)/d(tvec) is d(pixel)/d(point)
    np.testing.assert_allclose(J, cvJ[:, 3:6].reshape(-1, 2, 3), rtol=1e-6, atol=1e-6)


def test_bundle_jacobian_matches_finite_differences_and_its_sparsity(session):
    obs, _, sol = session
    sensors = bundle.SensorModels.from_observations(obs)
    flat = bundle.FlatObservations.from_points(obs.points_px)
    keep = np.isin(flat.set_index, [100, 101, 300, 500])
    sub = bundle.FlatObservations(
        flat.set_index[keep], flat.sensor[keep], flat.sphere[keep], flat.px[keep]
    )
    cal = sol.calibration
    R = np.stack([cal.sensor(sn, "left").pose.R for sn in obs.camera_serials])
    t = np.stack([cal.sensor(sn, "left").pose.t_m for sn in obs.camera_serials])
    n = len(obs.set_unix_ns)
    state = bundle.RigState(R, t, np.full((n, 3), np.nan), np.full((n, 3), np.nan))
    offsets = np.array([-0.2, -0.05, 0.25])
    linear.init_wands(state, np.unique(sub.set_index), linear.normalised(obs), sensors, offsets)
    problem = bundle.BundleProblem(
        state, sub, sensors, offsets, np.unique(sub.set_index), free_cameras=(0, 2, 3)
    )
    x = problem.x0() + np.random.default_rng(0).normal(0, 1e-3, problem.n_params)
    analytic = problem.jac(x).toarray()
    numeric = np.empty_like(analytic)
    for i in range(len(x)):  # central differences, the slow obvious twin
        step = np.zeros_like(x)
        step[i] = 1e-6
        numeric[:, i] = (problem.fun(x + step) - problem.fun(x - step)) / 2e-6
    np.testing.assert_allclose(analytic, numeric, atol=2e-4 * np.abs(numeric).max())
    outside = (analytic != 0) & (problem.sparsity().toarray() == 0)
    assert not outside.any()


# ---- accuracy -------------------------------------------------------------------------------


def test_solve_recovers_the_rig_within_the_goals(session, wand_world):
    obs, _, sol = session
    cal = sol.calibration
    assert len(cal.sensors) == 8
    errors = relative_errors(wand_world, cal, sol.reference_serial)
    for sn, (rot_deg, trans_mm) in errors.items():
        print(f"SN{sn}: rotation {rot_deg:.4f} deg, translation {trans_mm:.3f} mm")
        assert rot_deg <= 0.05, f"SN{sn} rotation off by {rot_deg:.3f} deg"
        assert trans_mm <= 2.0, f"SN{sn} translation off by {trans_mm:.2f} mm"
    q = cal.quality
    print({k: q[k] for k in ("reprojection_px_mean", "wand_score", "scale_check_ratio")})
    assert q["reprojection_px_mean"] <= 0.3
    assert q["wand_score"] <= 0.5
    assert abs(q["wand_length_mm_mean"] - 450.0) < 0.5
    assert abs(q["scale_check_ratio"] - 1.0) < 0.002
    assert q["verdict"] == "pass"
    for sn in obs.camera_serials:
        st = obs.stereo[sn]
        left, right = cal.sensor(sn, "left"), cal.sensor(sn, "right")
        expected = st.right_from_left.compose(left.pose)
        np.testing.assert_allclose(right.pose.matrix, expected.matrix, atol=1e-12)
        assert right.intrinsics == st.right
        for s in (left, right):
            assert s.stats["reprojection_px_mean"] <= 0.3
            assert s.stats["frames_used"] > 100
    # the file round-trips with every number the solver wrote
    again = RigCalibration.from_toml(cal.to_toml())
    assert again.quality["wand_score"] == q["wand_score"]


def test_injected_outliers_are_flagged(session):
    obs, outliers, sol = session
    r = sol.residuals
    injected = outliers[r.set_index, r.sensor_index, r.sphere_index]
    assert injected.sum() > 100
    assert not r.inlier[injected].any(), "an outlier of 5-30 px was kept"
    assert r.inlier[~injected].mean() > 0.98
    assert np.nanmax(r.error_px[r.inlier]) < 1.0
    assert sol.trajectory_m.shape == (len(obs.set_unix_ns), 3, 3)


def test_floor_frame_is_recovered(session, wand_world):
    obs, _, sol = session
    cal = sol.calibration
    assert cal.world_frame == "floor"
    t_s = (obs.set_unix_ns[sol.floor_sets] - SIM_EPOCH_UNIX_NS) / 1e9
    assert len(sol.floor_sets) >= 15 and t_s.max() <= 2.05
    for unit in wand_world.rig:
        est = cal.sensor(unit.serial, "left").pose
        # the world's up axis as each camera sees it, solved vs true
        cos = est.R[:, 2] @ unit.left_pose.R[:, 2]
        angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        height_mm = 1000 * (est.centre_m[2] - unit.left_pose.centre_m[2])
        print(f"SN{unit.serial}: floor normal {angle:.4f} deg, height {height_mm:+.2f} mm")
        assert angle <= 0.1
        assert abs(height_mm) <= 3.0
    # the wand's spheres rest one radius above z = 0
    on_floor = sol.trajectory_m[sol.floor_sets]
    np.testing.assert_allclose(on_floor[..., 2], obs.wand.radius_m, atol=0.002)


def test_two_floor_placements_fix_the_floor_plane_without_level_cameras(wand_world):
    """The wand laid down twice, crossing: the floor's normal comes from the centres alone."""
    radius = wand_world.config.wand.radius_m
    first = np.stack([wand_world.wand_centres(t) for t in np.arange(0.0, 2.0, 0.1)])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    second = (first[0] - first[0, 1]) @ turn.T + np.array([-0.8, 0.4, radius])
    waving = np.arange(5.0, 50.0, 0.1)
    moving = np.stack([wand_world.wand_centres(t) for t in waving])
    centres = np.concatenate([first, np.repeat(second[None], 20, axis=0), moving])
    times = np.concatenate([np.arange(0.0, 2.0, 0.1), np.arange(2.5, 4.5, 0.1), waving])
    obs, _ = synthesise(wand_world, times, centres=centres, seed=5)
    sol = solve(obs)
    q = sol.calibration.quality
    assert q["world_frame"] == "floor" and q["floor_normal_source"] == "wand placements"
    assert len(sol.floor_sets) >= 30
    for unit in wand_world.rig:
        est = sol.calibration.sensor(unit.serial, "left").pose
        cos = est.R[:, 2] @ unit.left_pose.R[:, 2]
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) <= 0.1
        assert abs(est.centre_m[2] - unit.left_pose.centre_m[2]) <= 0.003


def test_thinning_keeps_a_sparsely_seen_camera():
    n = 5000
    cam_seen = np.zeros((n, 4), bool)
    cam_seen[:, :3] = True
    cam_seen[::250, 3] = True  # camera 3 sees the wand in 20 sets only
    kept = thin_sets(np.arange(n), cam_seen, 400)
    assert len(kept) <= 400
    assert cam_seen[kept, 3].sum() == 20
    assert np.diff(kept).max() < 40  # still spread over the whole session


def test_without_floor_sets_the_reference_camera_is_the_world(wand_world):
    obs, _ = synthesise(wand_world, np.arange(5.0, 45.0, 0.1), seed=3)
    sol = solve(obs, SolveConfig(reference_serial=obs.camera_serials[1]))
    cal = sol.calibration
    assert sol.reference_serial == obs.camera_serials[1]
    assert cal.world_frame == f"camera:SN{obs.camera_serials[1]}-left"
    assert len(sol.floor_sets) == 0
    np.testing.assert_allclose(cal.sensor(sol.reference_serial, "left").pose.matrix, np.eye(4))
    for rot_deg, trans_mm in relative_errors(wand_world, cal, sol.reference_serial).values():
        assert rot_deg <= 0.05 and trans_mm <= 2.0


def test_essential_matrix_start_when_a_camera_has_no_stereo_pair(wand_world, session):
    obs, _, _ = session
    points = obs.points_px.copy()
    points[:, 3] = np.nan  # camera 1's right sensor: never seen
    sol = solve(with_points(obs, points))
    serial = obs.camera_serials[1]
    assert sol.start[serial].startswith("essential matrix")
    assert np.isnan(sol.calibration.quality[f"scale_check_ratio_SN{serial}"])
    for sn, (rot_deg, trans_mm) in relative_errors(
        wand_world, sol.calibration, sol.reference_serial
    ).items():
        print(f"SN{sn}: rotation {rot_deg:.4f} deg, translation {trans_mm:.3f} mm")
        assert rot_deg <= 0.05 and trans_mm <= 2.0


# ---- what a user is told --------------------------------------------------------------------


def test_a_camera_with_few_sets_is_named(session):
    obs, _, _ = session
    points = obs.points_px.copy()
    sees = np.flatnonzero(np.isfinite(points[:, 4:6]).all(axis=(2, 3)).any(axis=1))
    points[sees[5:], 4:6] = np.nan  # camera 2 keeps 5 sets
    with pytest.raises(SolveError, match=f"SN{obs.camera_serials[2]} \\(5 sets\\)"):
        solve(with_points(obs, points))


def test_a_camera_never_seen_with_another_is_named(session):
    obs, _, _ = session
    points = obs.points_px.copy()
    sees = np.isfinite(points[:, 6:8]).all(axis=(2, 3)).any(axis=1)
    alone = sees & (np.arange(len(sees)) % 2 == 0)
    points[alone, :6] = np.nan  # camera 3 sees the wand only when no other camera does
    points[~alone, 6:8] = np.nan
    with pytest.raises(SolveError, match=f"SN{obs.camera_serials[3]} never sees the wand"):
        solve(with_points(obs, points))


def test_a_wrong_wand_spec_is_reported_with_measured_and_expected(session):
    obs, _, _ = session
    wrong = WandSpec(sphere_positions_mm=(0.0, 200.0, 500.0))
    with pytest.raises(SolveError, match="200/300/500 mm") as info:
        solve(dataclasses.replace(obs, wand=wrong))
    message = str(info.value)
    assert re.search(r"measures 1[45]\d/[23]\d\d/4[45]\d mm", message)  # the true 150/300/450
    assert "wand.toml" in message
    assert all(f"SN{sn}" in message for sn in obs.camera_serials)


def test_a_wand_that_never_moves_is_degenerate(wand_world):
    obs, _ = synthesise(wand_world, np.arange(0.0, 2.0, 1 / 30), outlier_fraction=0.0)
    with pytest.raises(SolveError, match="degenerate") as info:
        solve(obs)
    assert "SN" in str(info.value)


def test_bad_config_names_the_field():
    with pytest.raises(ConfigError, match="cutoffs_px"):
        SolveConfig(cutoffs_px=(1.0, 5.0))
    with pytest.raises(ConfigError, match="loss"):
        SolveConfig(loss="l2")


# ---- speed ----------------------------------------------------------------------------------


def test_a_two_minute_session_at_30_fps(wand_world):
    obs, _ = synthesise(wand_world, np.arange(0.0, 120.0, 1 / 30), seed=7)
    assert obs.points_px.shape == (3600, 8, 3, 2)
    started = time.perf_counter()
    sol = solve(obs)
    seconds = time.perf_counter() - started
    q = sol.calibration.quality
    print(
        f"3600 sets x 8 sensors solved in {seconds:.1f} s (bundle over {q['sets_bundle']} sets); "
        f"reprojection {q['reprojection_px_mean']:.3f} px, wand score {q['wand_score']:.3f} %"
    )
    assert q["sets_fitted"] > 3000
    for sn, (rot_deg, trans_mm) in relative_errors(
        wand_world, sol.calibration, sol.reference_serial
    ).items():
        print(f"SN{sn}: rotation {rot_deg:.4f} deg, translation {trans_mm:.3f} mm")
        assert rot_deg <= 0.05 and trans_mm <= 2.0
