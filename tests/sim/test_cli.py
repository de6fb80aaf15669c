"""``egosurg sim`` and ``egosurg demo`` as a user runs them: real subprocesses, real files."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from protocol.formats.trajectory import read_trajectories
from protocol.formats.zed_conf import ZedFactoryCalibration
from reconstructor.replay.names import names_in
from sim.world import World
from tests.helpers import run_egosurg


def test_help_lists_the_commands():
    out = run_egosurg("--help")
    assert out.returncode == 0
    assert "sim" in out.stdout and "demo" in out.stdout


def test_frames_follow_the_cameras_clocks(tmp_path):
    out = run_egosurg(
        "sim",
        "frames",
        "--out",
        str(tmp_path),
        "--t-start",
        "0",
        "--t-end",
        "0.1",
        "--cameras",
        "1",
        "--resolution",
        "SVGA",
        "--depth",
        "--seed",
        "2",
    )
    assert out.returncode == 0, out.stderr
    rows = list(csv.DictReader(open(tmp_path / "truth.csv")))
    assert len(rows) in (3, 4)  # 30 fps over 0.1 s, at the camera's own phase
    serial = rows[0]["camera_serial"]
    for row in rows:
        stem = tmp_path / f"SN{serial}" / f"left_{int(row['frame_index']):06d}"
        if row["dropped"] == "1":
            assert not stem.with_suffix(".png").exists()
            continue
        img = cv2.imread(str(stem.with_suffix(".png")))
        assert img.shape == (600, 960, 3)
        depth = cv2.imread(str(stem) + "_depth_mm.png", cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and 500 < np.median(depth) < 9000
        assert (tmp_path / f"SN{serial}" / f"right_{int(row['frame_index']):06d}.png").exists()
    # the factory files come with the frames
    ZedFactoryCalibration.read(tmp_path / f"SN{serial}.conf")


def test_factory_and_wand_files(tmp_path):
    out = run_egosurg("sim", "factory", "--out", str(tmp_path / "f"))
    assert out.returncode == 0, out.stderr
    confs = sorted((tmp_path / "f").glob("SN*.conf"))
    assert len(confs) == 4
    out = run_egosurg("sim", "wand-file", "--out", str(tmp_path / "wand.toml"))
    assert out.returncode == 0
    from protocol.formats.wand import WandSpec

    assert WandSpec.read(tmp_path / "wand.toml") == WandSpec()


def test_view_renders_a_person_and_an_arbitrary_camera(tmp_path):
    ego = tmp_path / "ego.png"
    out = run_egosurg(
        "sim", "view", "--out", str(ego), "--t", "2", "--person", "surgeon", "--size", "320x200"
    )
    assert out.returncode == 0, out.stderr
    assert cv2.imread(str(ego)).shape == (200, 320, 3)
    side = tmp_path / "side.png"
    out = run_egosurg(
        "sim",
        "view",
        "--out",
        str(side),
        "--t",
        "2",
        "--eye",
        "3,0,1.7",
        "--look-at",
        "0,0,1",
        "--size",
        "320x200",
        "--depth-out",
        str(tmp_path / "d.png"),
    )
    assert out.returncode == 0, out.stderr
    assert cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED).max() > 1000


@pytest.mark.parametrize(
    ("command", "words"),
    [
        ("sim frames --out {tmp} --resolution 4K", ["4K", "HD1200"]),
        ("sim view --out {tmp}/v.png --t -1 --person surgeon", ["-1", "time"]),
        ("sim view --out {tmp}/v.png --t 1 --eye 9,0,1.5 --look-at 0,0,1", ["outside the room"]),
        ("sim view --out {tmp}/v.png --t 1 --person nobody", ["nobody", "surgeon"]),
        ("sim view --out {tmp}/v.png --t 1 --eye 1,2 --look-at 0,0,1", ["three"]),
        ("sim frames --out {tmp} --t-start 1 --t-end 0.5", ["ends before it starts"]),
    ],
)
def test_bad_input_gets_one_clear_line_not_a_traceback(tmp_path, command, words):
    out = run_egosurg(*[a.replace("{tmp}", str(tmp_path)) for a in command.split()])
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    for w in words:
        assert w in out.stderr


def test_malformed_conf_is_reported_by_name(tmp_path):
    bad = tmp_path / "SN123.conf"
    bad.write_text("[LEFT_CAM_FHD1200]\nfx=abc\n")
    snippet = (
        f"from protocol.formats.zed_conf import ZedFactoryCalibration as Z\nZ.read({str(bad)!r})\n"
    )
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", snippet], capture_output=True, text=True)
    assert "SN123.conf" in out.stderr and "fx" in out.stderr


@pytest.mark.slow  # the whole reconstruction chain
@pytest.mark.timeout(2400)
def test_demo_runs_every_stage(tmp_path):
    out = run_egosurg(
        "demo", "--out", str(tmp_path), "--record-s", "12", "--steps", "10", timeout=2300,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "[3/8] calibration" in out.stdout and "[4/8] reconstruction" in out.stdout
    # stage 3 calibrated the rig from its wand session (the default length, on the report's
    # own thresholds: a newcomer sees it pass), and stage 4 used that calibration
    assert "against the simulator's true rig" in out.stdout, out.stdout + out.stderr
    assert "verdict: PASS" in out.stdout, out.stdout
    assert "calibration: stage 3's wand calibration" in out.stdout
    # stage 4 reconstructed a timestamp and put a person's view beside the truth
    assert list((tmp_path / "recon").glob("t*/splats.ply"))
    assert list((tmp_path / "recon").glob("*_view_vs_truth.png"))
    # stage 5 printed the egocentric table of that timestamp, one row per method
    assert "[5/8] evaluation" in out.stdout
    for row in ("| Depth reprojection |", "| EgoSurg w/o refinement |", "| EgoSurg (guided"):
        assert row in out.stdout, row
    assert list((tmp_path / "evaluation" / "egocentric").glob("*.md"))
    # stage 6 reconstructed a few timestamps as a case; stage 7 replayed and tested a sightline
    assert "[6/8] batch" in out.stdout and "[7/8] review" in out.stdout
    # the case's timestamps are a second apart: the sim renders the people once a second, so
    # closer ones would be the same picture (the demo says so on screen)
    index = json.loads((tmp_path / "case" / "case.json").read_text())
    times_s = sorted(float(e["t_s"]) for e in index["timestamps"])
    assert len(times_s) == 3 and np.allclose(np.diff(times_s), 1.0, atol=0.01), times_s
    assert "renders the people's motion 1 time(s) a second" in out.stdout
    # stage 7 reviewed with estimated roles: the people found in the session (12 s: 10
    # timestamps a second apart or more, what 'egosurg people' needs to learn the room from),
    # their tracks named by the sim's truth (said on screen), the roles file written by
    # 'egosurg people name': each role is one track or several joined, estimated keyframes
    # with their confidences
    assert "SIMULATOR'S TRUTH, for the demo only" in out.stdout, out.stdout
    tracks = read_trajectories(tmp_path / "review" / "people.toml")
    roles = read_trajectories(tmp_path / "review" / "roles.toml")
    people_in_room = World.from_seed(0, phase="intraoperative").head_poses(0.0)
    assert roles and {r.name for r in roles} <= set(people_in_room)
    joined = names_in(roles, tracks, "review/roles.toml")  # refuses a role no tracks make
    assert set(joined.values()) == {r.name for r in roles}
    for role in roles:
        assert all(k.confidence is not None for k in role.keyframes)
    (replay_path,) = (tmp_path / "review").glob("*.mp4")
    assert replay_path.stem in {r.name for r in roles}
    replay = cv2.VideoCapture(str(replay_path))
    assert replay.get(cv2.CAP_PROP_FRAME_COUNT) >= 2
    assert (tmp_path / "review" / "sightline" / "sightline.csv").exists()
    # stage 8: the case report, one self-contained file
    assert "[8/8] report" in out.stdout
    report = (tmp_path / "review" / "report.html").read_text()
    assert "<html" in report.lower() and "demo-case" in report
    mosaic = cv2.imread(str(tmp_path / "sim" / "rig_views.png"))
    assert mosaic.shape[0] > 4 * 200 and mosaic.shape[1] >= 2 * 480  # eight views, 4 x 2
    assert cv2.imread(str(tmp_path / "sim" / "room_topdown.png")) is not None
    video = cv2.VideoCapture(str(tmp_path / "sim" / "ground_truth.mp4"))
    assert video.get(cv2.CAP_PROP_FRAME_COUNT) >= 20
    for name in ("rig_views.png", "room_topdown.png", "ground_truth.mp4"):
        assert name in out.stdout  # the demo says where it wrote them
    # the capture stage recorded a session through real agent and recorder processes
    sessions = list((tmp_path / "capture" / "sessions").glob("*.h5"))
    assert len(sessions) == 1 and str(sessions[0]) in out.stdout
    assert "closed cleanly" in out.stdout and "synchronised sets" in out.stdout
