"""The calibration report on synthetic data: the simulator's rig, a wand waved through the room,
and detections with known noise."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from calibration.report.page import PICTURES, write_report
from calibration.report.stats import ReportData, sensor_stats
from calibration.report.thresholds import Thresholds
from calibration.report.verdict import annotate, quality_table, verdict
from protocol.formats.rig_calibration import RigCalibration

SPEC_MM = 450.0
SPHERES_M = np.array([0.0, 0.150, 0.450])


@pytest.fixture(scope="module")
def rig(sim_true_rig: RigCalibration) -> RigCalibration:
    return sim_true_rig


def synthetic(
    rig: RigCalibration,
    *,
    noise_px: float = 0.25,
    n_sets: int = 600,
    length_sd_mm: float = 0.4,
    cutoff_px: float = 3.0,
    seed: int = 0,
) -> ReportData:
    """A wand waved through the whole reachable volume; each visible sphere is detected at its
    true projection plus Gaussian noise of ``noise_px`` per axis. The solver is played by taking
    the truth as the solution: the residual is the noise, inliers are under ``cutoff_px``."""
    rng = np.random.default_rng(seed)
    first = np.column_stack(
        [
            rng.uniform(-2.8, 2.8, n_sets),
            rng.uniform(-2.6, 2.6, n_sets),
            rng.uniform(0.2, 2.2, n_sets),
        ]
    )
    d = rng.normal(size=(n_sets, 3)) * [1, 1, 0.5]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    traj = first[:, None, :] + SPHERES_M[None, :, None] * d[:, None, :]  # (N, 3, 3)
    names = tuple(s.name for s in rig.sensors)
    obs_sensor, obs_px, obs_res, obs_set = [], [], [], []
    frames = {}
    for k, s in enumerate(rig.sensors):
        px, z = s.camera.project(traj.reshape(-1, 3))
        i = s.intrinsics
        inside = (z > 0.3) & (px[:, 0] >= 0) & (px[:, 0] < i.width_px)
        inside &= (px[:, 1] >= 0) & (px[:, 1] < i.height_px)
        ok = inside.reshape(n_sets, 3).all(axis=1)  # a frame counts when all three spheres are seen
        sets = np.flatnonzero(ok)
        noise = rng.normal(scale=noise_px, size=(len(sets) * 3, 2))
        obs_sensor.append(np.full(len(sets) * 3, k))
        obs_px.append(px.reshape(n_sets, 3, 2)[sets].reshape(-1, 2) + noise)
        obs_res.append(noise)
        obs_set.append(np.repeat(sets, 3))
        frames[s.name] = (len(sets), 7, {"two blobs merged": 4, "mislabelled": 3})
    res = np.concatenate(obs_res)
    return ReportData(
        calibration=rig,
        sensor_names=names,
        obs_sensor=np.concatenate(obs_sensor),
        obs_px=np.concatenate(obs_px),
        obs_residual_px=res,
        obs_inlier=np.hypot(res[:, 0], res[:, 1]) < cutoff_px,
        obs_set=np.concatenate(obs_set),
        wand_length_mm=SPEC_MM + rng.normal(scale=length_sd_mm, size=n_sets),
        wand_spec_length_mm=SPEC_MM,
        frames=frames,
        wand_trajectory_m=traj,
    )


@pytest.fixture(scope="module")
def good(rig) -> ReportData:
    return synthetic(rig)


def _only(data: ReportData, keep: np.ndarray) -> ReportData:
    """``data`` with only the observations ``keep`` (M,) marks."""
    return replace(
        data,
        obs_sensor=data.obs_sensor[keep],
        obs_px=data.obs_px[keep],
        obs_residual_px=data.obs_residual_px[keep],
        obs_inlier=data.obs_inlier[keep],
        obs_set=data.obs_set[keep] if data.obs_set is not None else None,
    )


def test_good_data_passes_and_the_report_is_written(good, tmp_path):
    passed, reasons = verdict(good)
    assert passed, reasons
    assert reasons == []
    page = write_report(good, tmp_path)
    assert page == tmp_path / "report.html"
    text = page.read_text()
    assert "PASSED" in text and "FAILED" not in text
    assert text.count("data:image/png;base64,") == len(PICTURES)
    for name in PICTURES.values():
        png = (tmp_path / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    for s in good.sensors:
        assert s.name in text


def test_two_pixel_noise_fails_with_readable_reasons(rig, tmp_path):
    bad = synthetic(rig, noise_px=2.0, length_sd_mm=6.0)
    passed, reasons = verdict(bad)
    assert not passed
    text = "\n".join(reasons)
    assert "The rig as a whole: spheres appear on average" in text
    assert "limit 0.50 px" in text and "wand score" in text
    assert len(reasons) <= 10, reasons  # grouped by check, not eight copies of each
    assert "All 8 sensors: mean reprojection error" in text
    page = write_report(bad, tmp_path).read_text()
    assert "FAILED: do not use this calibration" in page
    assert "The rig as a whole" in page


def test_too_few_frames_fails(rig):
    passed, reasons = verdict(synthetic(rig, n_sets=60, seed=1))
    assert not passed
    few = [r for r in reasons if "usable frames (need at least 100)" in r]
    assert len(few) == 1  # one reason per failed check, naming every sensor that failed it
    assert few[0].startswith("All 8 sensors saw the wand in only")
    assert "Wave the wand longer where these cameras can see it" in few[0]


def test_a_sensor_seen_in_half_its_image_fails_coverage(good):
    name = good.sensor_names[2]
    w = good.image_size[name][0]
    keep = ~((good.obs_sensor == 2) & (good.obs_px[:, 0] > w / 2))
    half = _only(good, keep)
    passed, reasons = verdict(half)
    assert not passed
    assert len(reasons) == 1, reasons
    assert reasons[0].startswith(f"Camera {name}: the wand reached only")
    assert "of the 16 regions of its image (need 9)" in reasons[0]
    assert sensor_stats(half)[name]["coverage_cells"] <= 8


def test_a_sensor_that_never_saw_the_wand_is_named(good):
    keep = good.obs_sensor != 5
    none = replace(_only(good, keep), obs_set=None)
    passed, reasons = verdict(none)
    assert not passed
    assert reasons == [
        f"Camera {good.sensor_names[5]} never saw the wand. Check that it was recording and not "
        "covered, and wave the wand in its view; then record the wand session again."
    ]


def test_quality_numbers_equal_numpy_on_the_same_arrays(good):
    q = quality_table(good)
    r = np.hypot(*good.obs_residual_px[good.obs_inlier].T)
    assert q["reprojection_px_mean"] == pytest.approx(np.mean(r), rel=1e-12)
    assert q["reprojection_px_rms"] == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-12)
    assert q["reprojection_px_median"] == pytest.approx(np.median(r), rel=1e-12)
    assert q["reprojection_px_p95"] == pytest.approx(np.percentile(r, 95), rel=1e-12)
    wl = good.wand_length_mm
    assert q["wand_length_mm_mean"] == pytest.approx(np.mean(wl), rel=1e-12)
    assert q["wand_length_mm_sd"] == pytest.approx(np.std(wl, ddof=1), rel=1e-12)
    assert q["wand_score"] == pytest.approx(100 * np.std(wl, ddof=1) / np.mean(wl), rel=1e-12)
    assert q["verdict"] == "pass"
    assert q["inliers"] == good.obs_inlier.sum() and q["observations"] == len(good.obs_inlier)
    # the noise is known: mean of a Rayleigh magnitude = sigma * sqrt(pi / 2)
    assert q["reprojection_px_mean"] == pytest.approx(0.25 * math.sqrt(math.pi / 2), rel=0.03)

    stats = sensor_stats(good)
    for k, name in enumerate(good.sensor_names):
        sel = (good.obs_sensor == k) & good.obs_inlier
        rk = np.hypot(*good.obs_residual_px[sel].T)
        st = stats[name]
        assert st["reprojection_px_mean"] == pytest.approx(np.mean(rk), rel=1e-12)
        assert st["reprojection_px_p95"] == pytest.approx(np.percentile(rk, 95), rel=1e-12)
        assert st["inliers"] == sel.sum()
        assert st["inlier_frames"] == len(np.unique(good.obs_set[sel]))
        assert st["frames_rejected"] == 7


def test_annotated_calibration_carries_quality_into_the_toml(good):
    cal = annotate(good)
    back = RigCalibration.from_toml(cal.to_toml())
    assert back.quality["verdict"] == "pass"
    assert back.quality["wand_score"] == quality_table(good)["wand_score"]
    name = good.sensor_names[0]
    assert (
        back.sensors[0].stats["reprojection_px_mean"]
        == sensor_stats(good)[name]["reprojection_px_mean"]
    )


def test_thresholds_and_report_data_are_validated(good):
    with pytest.raises(ValueError, match=r"Thresholds\.mean_px"):
        Thresholds(mean_px=-1)
    with pytest.raises(ValueError, match="min_coverage_cells"):
        Thresholds(min_coverage_cells=17)
    with pytest.raises(ValueError, match=r"ReportData.obs_px has shape \(3, 3\)"):
        replace(good, obs_sensor=np.zeros(3, int), obs_px=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="not in the calibration"):
        replace(good, sensor_names=(*good.sensor_names[:-1], "SN1-left"))
    # thresholds passed in override the data's own
    assert verdict(good, replace(good.thresholds, min_frames=10_000))[0] is False


def test_a_session_without_any_detection_still_gets_a_report(rig, tmp_path):
    empty = ReportData(
        calibration=rig,
        sensor_names=tuple(s.name for s in rig.sensors),
        obs_sensor=np.zeros(0, int),
        obs_px=np.zeros((0, 2)),
        obs_residual_px=np.zeros((0, 2)),
        obs_inlier=np.zeros(0, bool),
        wand_length_mm=np.zeros(0),
        wand_spec_length_mm=SPEC_MM,
    )
    passed, reasons = verdict(empty)
    assert not passed
    assert reasons[0].startswith("The rig as a whole: no wand detection could be used")
    assert reasons[-1].startswith("All 8 sensors never saw the wand")
    assert not any("nan" in r for r in reasons)
    assert math.isnan(quality_table(empty)["reprojection_px_mean"])
    assert "FAILED" in write_report(empty, tmp_path).read_text()
