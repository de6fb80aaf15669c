"""The reconstructor end to end on a session recorded through the real agents and recorder, run
through the real ``egosurg reconstruct`` / ``egosurg render`` commands, and its errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol.session import SessionReader
from reconstructor.splats import ply
from sim import World
from sim.deploy import SimRigSpec
from sim.truth import true_rig_calibration
from tests.helpers import (
    copy_sets,
    record_sim_session,
    run_egosurg,
    sim_identity,
    sim_reader_env,
)

SEED = 2
PHASE = "intraoperative"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    """About 3 s of the OR at SVGA 15 fps, sealed for the sim's site key (the readers below run
    with its identity in ``EGOSURG_IDENTITY``), and the sim's true calibration beside it."""
    spec = SimRigSpec(
        seed=SEED,
        phase=PHASE,
        resolution="SVGA",
        fps=15.0,
        content_fps=15.0,
        prerender_s=2.0,
        drop_probability=0.0,
        jpeg_quality=95,
    )
    session = record_sim_session(tmp_path_factory.mktemp("reconrig"), spec, "recon", 3.0)
    calibration = session.parent / "calibration.toml"
    true_rig_calibration(World.from_seed(SEED, phase=PHASE)).write(calibration)
    return session, calibration


@pytest.mark.slow  # the whole reconstruction chain
def test_one_timestamp_reconstructs_end_to_end_and_renders(recorded, tmp_path):
    session, calibration = recorded
    out = tmp_path / "recon"
    done = run_egosurg(
        "reconstruct", str(session), "--calibration", str(calibration), "--at", "1.0",
        "--out", str(out), "--steps", "60", "--train-views", "left", "--evaluate",
        timeout=900, env=sim_reader_env(session),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    run = next(out.iterdir())
    for name in ("splats.ply", "config.toml", "log.txt", "summary.json", "eval.md", "eval.csv"):
        assert (run / name).exists(), name
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps"] == 60 and len(summary["held_out_views"]) == 4
    model = ply.read_ply(run / "splats.ply")
    assert model.num == summary["gaussians"] > 5_000
    # the run's config file repeats the run's settings
    assert 'train_views = "left"' in (run / "config.toml").read_text()

    # held-out right cameras: after only 60 steps the splats already beat drawing the fused
    # points directly, by far (measured: 14.5 dB against 7.3 dB)
    rows = [line.split(",") for line in (run / "eval.csv").read_text().splitlines()[1:]]
    by_method: dict[str, list[float]] = {}
    for _protocol, _view, method, psnr_db, _ssim in rows:
        by_method.setdefault(method, []).append(float(psnr_db))
    splats = np.mean(by_method["egosurg (splats)"])
    baseline = np.mean(by_method["depth reprojection"])
    print(f"near-field after 60 steps: splats {splats:.2f} dB, depth reprojection {baseline:.2f}")
    assert splats > baseline + 4.0 and splats > 12.0

    # a held-out camera rendered by name, and a virtual camera given by eye and target
    sensor = summary["held_out_views"][0]
    view = tmp_path / "view.png"
    done = run_egosurg("render", str(run / "splats.ply"), "--camera", sensor, "--out", str(view))
    assert done.returncode == 0, done.stderr[-2000:]
    img = cv2.imread(str(view))
    assert img.shape == (600, 960, 3) and img.std() > 10
    done = run_egosurg(
        "render", str(run / "splats.ply"), "--camera", "eye=2.5,-2.0,1.7 target=0,0,1",
        "--size", "480x300", "--out", str(view),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert cv2.imread(str(view)).shape == (300, 480, 3)


def test_a_session_without_a_calibration_is_refused(recorded, tmp_path):
    session, _ = recorded
    lone = tmp_path / "lone.h5"
    lone.write_bytes(session.read_bytes())
    done = run_egosurg(
        "reconstruct", str(lone), "--at", "1.0", "--out", str(tmp_path / "o"),
        env=sim_reader_env(session),
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "calibration" in done.stderr and "egosurg calibrate" in done.stderr


def test_a_time_out_of_range_names_the_valid_range(recorded, tmp_path):
    session, calibration = recorded
    for at in ("600", "set:100000"):
        done = run_egosurg(
            "reconstruct", str(session), "--calibration", str(calibration), "--at", at,
            "--out", str(tmp_path / "o"), env=sim_reader_env(session),
        )  # fmt: skip
        assert done.returncode == 2 and "Traceback" not in done.stderr
        assert "out of range" in done.stderr and "set:0 to set:" in done.stderr


@pytest.mark.slow  # the whole reconstruction chain
def test_a_set_with_a_missing_camera_reconstructs_from_the_rest(recorded, tmp_path):
    session, calibration = recorded
    partial = tmp_path / "partial.h5"
    with SessionReader(session) as reader:
        k = len(reader.sets().set_unix_ns) // 2
        dropped = reader.info.camera_serials[-1]
    copy_sets(session, partial, np.array([k]), drop_serial=dropped, identity=sim_identity(session))
    out = tmp_path / "o"
    done = run_egosurg(
        "reconstruct", str(partial), "--calibration", str(calibration), "--at", "set:0",
        "--out", str(out), "--steps", "2",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"SN{dropped}" in done.stderr and "missing" in done.stderr
    summary = json.loads(next(out.iterdir()).joinpath("summary.json").read_text())
    assert summary["missing_cameras"] == [f"SN{dropped}"] and len(summary["sensors"]) == 6


def test_rendering_a_ply_that_is_not_a_splat_file_is_refused(tmp_path):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.random.default_rng(0).random((50, 3)))
    path = tmp_path / "points.ply"
    o3d.io.write_point_cloud(str(path), cloud)
    done = run_egosurg(
        "render", str(path), "--camera", "eye=2,2,2 target=0,0,0", "--out", str(tmp_path / "v.png")
    )
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "points.ply" in done.stderr and "splat" in done.stderr
