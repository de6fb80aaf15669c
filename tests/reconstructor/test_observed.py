"""Observed versus inferred (reconstructor/replay/observed.py): which Gaussians the input cameras
saw, and the per-pixel observed map, on tiny scenes built by hand and drawn by the real
rasterizer; then the flags ``egosurg replay --observed`` and ``egosurg sightline`` write, on a
hand-built case folder whose timestamps were trained on two cameras and on one."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from protocol.camera import Camera, Intrinsics, Pose
from protocol.formats.rig_calibration import RigCalibration, SensorCalibration
from protocol.formats.site import SiteBox, site_toml
from protocol.formats.trajectory import Keyframe, Trajectory, write_trajectories
from reconstructor.case.index import CaseIndex, Entry, checksum_file
from reconstructor.errors import ObservedError
from reconstructor.raster import RasterConfig
from reconstructor.replay.observed import (
    ObservedConfig,
    observation_counts,
    observed_map,
    run_input_cameras,
    seen_by,
)
from reconstructor.splats import ply
from reconstructor.splats.gaussians import Gaussians

RASTER = RasterConfig()
CONFIG = ObservedConfig(visibility_width_px=96)


def gaussians(means, scales_m, opacity: float = 0.95) -> Gaussians:
    """Round (or per-axis) Gaussians at ``means``, grey, of one opacity."""
    m = torch.tensor(means, dtype=torch.float32).reshape(-1, 3)
    s = torch.tensor(scales_m, dtype=torch.float32).expand(len(m), 3).clone()
    logit = float(np.log(opacity / (1 - opacity)))
    return Gaussians(
        means_m=m,
        quats_wxyz=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(len(m), 1),
        log_scales=torch.log(s),
        opacity_logits=torch.full((len(m),), logit),
        sh_dc=torch.zeros(len(m), 3),
        sh_rest=torch.zeros(len(m), 0, 3),
    )


def camera(eye, target, name: str = "cam", size=(96, 72), fov_deg: float = 60.0) -> Camera:
    pose = Pose.look_at(np.array(eye, float), np.array(target, float))
    return Camera(name=name, intrinsics=Intrinsics.from_fov(*size, fov_deg), pose=pose)


def pixel(cam: Camera, point) -> tuple[int, int]:
    px, _ = cam.project(np.array([point], float))
    return round(float(px[0, 1])), round(float(px[0, 0]))  # (row, column)


# three input cameras side by side at x = 0, looking along +x at the point (3, 0, 1.5)
INPUTS = [camera((0.0, y, 1.5), (3.0, 0.0, 1.5), f"in{k}") for k, y in enumerate((-0.5, 0, 0.5))]


def test_a_gaussian_in_front_of_every_camera_is_seen_by_all_and_one_behind_them_by_none():
    g = gaussians([[3.0, 0.0, 1.5], [-3.0, 0.0, 1.5], [3.0, 9.0, 1.5]], [0.05])
    counts = observation_counts(g, INPUTS, RASTER, CONFIG)
    # in front of all three; behind all three; in front but far outside every image
    assert counts.tolist() == [3, 0, 0]


def test_a_gaussian_hidden_behind_a_wall_is_not_counted_for_the_camera_it_is_hidden_from():
    front = camera((0.0, 0.0, 1.5), (5.0, 0.0, 1.5), "front")
    side = camera((3.5, -2.0, 1.5), (3.5, 0.0, 1.5), "side")  # the wall is outside its image
    hidden, wall = [3.5, 0.0, 1.5], [2.0, 0.0, 1.5]
    alone = gaussians([hidden], [0.03])
    assert seen_by(alone, front, RASTER, CONFIG).tolist() == [True]  # nothing in the way yet
    g = gaussians([hidden, wall], [[0.03] * 3, [0.02, 0.4, 0.4]], opacity=0.99)
    assert seen_by(g, front, RASTER, CONFIG).tolist() == [False, True]
    assert seen_by(g, side, RASTER, CONFIG).tolist() == [True, False]
    assert observation_counts(g, [front, side], RASTER, CONFIG).tolist() == [1, 1]


def test_the_observed_map_is_high_on_well_observed_content_and_zero_on_inferred():
    """What a reviewer reads off the map: a Gaussian the input cameras saw shows as observed, one
    none of them saw as inferred, empty space as not observed; every value is in [0, 1]."""
    seen, unseen = [3.0, 0.0, 1.5], [-3.0, 0.0, 1.5]
    g = gaussians([seen, unseen], [0.3], opacity=0.9)
    counts = observation_counts(g, INPUTS, RASTER, CONFIG)
    assert counts.tolist() == [3, 0]
    novel = camera((0.0, -6.0, 1.5), (0.0, 0.0, 1.5), "novel", fov_deg=90.0)
    out = observed_map(g, counts, novel, RASTER, CONFIG)
    assert out.observed[pixel(novel, seen)] > 0.8
    assert out.views[pixel(novel, seen)] == pytest.approx(3.0, abs=1e-3)
    assert out.observed[pixel(novel, unseen)] < 1e-6 and out.alpha[pixel(novel, unseen)] > 0.8
    assert out.observed[0, 0] == 0.0 and out.alpha[0, 0] < 1e-3  # nothing there: not observed
    mask = out.well_observed(CONFIG)
    assert mask[pixel(novel, seen)] and not mask[pixel(novel, unseen)]


def test_the_observed_map_stays_in_zero_one_and_under_alpha_for_any_counts():
    rng = np.random.default_rng(0)
    means = rng.uniform([2.0, -1.0, 0.8], [4.0, 1.0, 2.2], size=(300, 3))
    g = gaussians(means.tolist(), [0.06], opacity=0.7)
    counts = rng.integers(0, 6, size=300)
    out = observed_map(g, counts, INPUTS[1], RASTER, ObservedConfig(min_views=3))
    assert out.observed.min() >= 0.0 and out.observed.max() <= 1.0
    assert np.all(out.observed <= out.alpha + 1e-5)
    assert 0.0 < out.share < 1.0


def test_the_input_cameras_are_the_sensors_the_run_trained_on(tmp_path):
    rig = _rig()
    rig.write(tmp_path / "calibration.toml")
    (tmp_path / "summary.json").write_text(json.dumps({"train_views": ["SN1-right"]}))
    cams = run_input_cameras(tmp_path)
    assert [c.name for c in cams] == ["SN1-right"]
    assert np.allclose(cams[0].pose.centre_m, rig.sensors[1].pose.centre_m)
    (tmp_path / "summary.json").write_text(json.dumps({"train_views": ["SN9-left"]}))
    with pytest.raises(ObservedError, match="does not hold"):
        run_input_cameras(tmp_path)
    (tmp_path / "summary.json").unlink()
    with pytest.raises(ObservedError, match=r"summary\.json is missing"):
        run_input_cameras(tmp_path)


def _rig() -> RigCalibration:
    intr = Intrinsics.from_fov(96, 72, 60.0)
    sensors = tuple(
        SensorCalibration(name=c.name, camera_serial=1, side=side, intrinsics=intr, pose=c.pose)
        for c, side in (
            (camera((0.0, 0.1, 1.5), (3.0, 0.1, 1.5), "SN1-left"), "left"),
            (camera((0.0, -0.1, 1.5), (3.0, -0.1, 1.5), "SN1-right"), "right"),
        )
    )
    return RigCalibration(sensors=sensors)


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    """Two timestamps of one wall of Gaussians at x = 3: t = 0 trained on both sensors of a
    stereo camera (observed), t = 1 on one of them (the same wall: inferred)."""
    root = tmp_path_factory.mktemp("observed_case")
    folder = root / "case"
    ys, zs = np.meshgrid(np.linspace(-1.2, 1.2, 13), np.linspace(0.6, 2.4, 10))
    wall = np.stack([np.full(ys.size, 3.0), ys.ravel(), zs.ravel()], 1)
    g = gaussians(wall.tolist(), [[0.02, 0.15, 0.15]], opacity=0.95)
    rig = _rig()
    entries = []
    for k, views in enumerate((["SN1-left", "SN1-right"], ["SN1-left"])):
        name = f"t{k:05d}.000"
        model = folder / "models" / f"{name}.ply"
        model.parent.mkdir(parents=True, exist_ok=True)
        ply.write_ply(model, g)
        digest, size = checksum_file(model)
        run = folder / "runs" / name
        rig.write(run / "calibration.toml")
        (run / "summary.json").write_text(json.dumps({"train_views": views}))
        entries.append(Entry(name=name, t_s=float(k), set_index=k, model=f"models/{name}.ply",
                             xxh3_64=digest, bytes=size, status="done"))  # fmt: skip
    CaseIndex(session=str(root / "absent.h5"), session_started_unix_ns=0, config_hash="x",
              warm_start=False, created_unix_ns=time.time_ns(),
              timestamps=tuple(entries)).write(folder)  # fmt: skip
    eye = (0.5, 0.0, 1.5)
    keys = tuple(Keyframe(time_s=t, eye_m=eye, look_at_m=(3.0, 0.0, 1.5), fov_deg=70.0)
                 for t in (0.0, 1.0))  # fmt: skip
    write_trajectories(root / "roles.toml", [Trajectory(name="viewer", keyframes=keys)])
    # a screen just behind the wall's middle: what the viewer's sightline rests on is the wall
    box = SiteBox(name="screen", centre_m=(3.2, 0.0, 1.5), size_m=(0.02, 0.6, 0.4), yaw_deg=180)
    (root / "site.toml").write_text(site_toml([box]))
    return folder


def test_replay_and_sightline_flag_the_instant_whose_model_one_camera_saw(case, tmp_path):
    from protocol.cli import main

    roles = str(case.parent / "roles.toml")
    out = tmp_path / "viewer.mp4"
    assert main(["replay", str(case), "--role", "viewer", "--roles", roles, "--out", str(out),
                 "--fps", "2", "--size", "96x64", "--observed"]) == 0  # fmt: skip
    assert out.is_file() and (tmp_path / "viewer.observed.mp4").stat().st_size > 0
    frames = list(csv.DictReader((tmp_path / "viewer.observed.csv").open()))
    assert [(f["model"], f["rests_on_inferred"]) for f in frames] == [
        ("t00000.000", "0"), ("t00000.000", "0"), ("t00001.000", "1")
    ]  # fmt: skip
    assert float(frames[0]["observed_share"]) > 0.5 and float(frames[2]["observed_share"]) == 0

    los = tmp_path / "los"
    site = str(case.parent / "site.toml")
    assert main(["sightline", str(case), "--viewer", "viewer", "--roles", roles, "--target",
                 "screen", "--site", site, "--out", str(los)]) == 0  # fmt: skip
    rows = list(csv.DictReader((los / "sightline.csv").open()))
    assert [r["rests_on_inferred"] for r in rows] == ["0", "1"]
    assert float(rows[0]["observed_share"]) > 0.5 and float(rows[1]["observed_share"]) == 0.0
