"""Replay and line of sight on a tiny reconstructed case (96 px, 3 steps, 3 timestamps), through
the real ``egosurg sim roles``, ``egosurg replay`` and ``egosurg sightline`` commands, and the
line-of-sight depth test against the simulator's ray-cast truth."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import av
import numpy as np
import pytest

from protocol.camera import Pose
from protocol.formats.site import read_site
from protocol.formats.trajectory import Keyframe, Trajectory, read_trajectories, write_trajectories
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.path import CameraPath
from tests.helpers import run_egosurg
from tests.reconstructor.tiny import tiny_config_toml, tiny_eval_session


class Ran:
    def __init__(self, returncode: int, stderr: str) -> None:
        self.returncode, self.stderr = returncode, stderr


def egosurg(capsys, *args: str) -> Ran:
    """The real dispatcher (protocol/cli.py), in this process: torch loads once per file."""
    from protocol.cli import main

    capsys.readouterr()
    code = main(list(args))
    return Ran(code, capsys.readouterr().err)


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict[str, Path]:
    """Four sets (2.0-2.2 s) of the intraoperative sim, a case of three timestamps, the sim's
    true roles and site boxes."""
    root = tmp_path_factory.mktemp("replay")
    h5 = tiny_eval_session(root, sets=4) / "session.h5"
    (root / "tiny.toml").write_text(tiny_config_toml(3))
    done = run_egosurg("reconstruct", str(h5), "--config", str(root / "tiny.toml"),
                       "--every", "0.0667s", "--out", str(root / "case"), timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    roles = run_egosurg("sim", "roles", str(h5), "--every", "0.05", "--out",
                        str(root / "roles.toml"), "--site-out", str(root / "site.toml"),
                        )  # fmt: skip
    assert roles.returncode == 0, roles.stderr
    bad = run_egosurg("sim", "roles", "--out", str(root / "x.toml"))
    assert bad.returncode == 2 and "give --from and --to" in bad.stderr
    return {"root": root, "case": root / "case", "roles": root / "roles.toml",
            "site": root / "site.toml", "session": h5}  # fmt: skip


def test_sim_roles_are_the_true_head_poses_at_each_keyframe(case):
    from sim.world import World

    world = World.from_seed(3, phase="intraoperative")
    roles = {t.name: t for t in read_trajectories(case["roles"])}
    assert "surgeon" in roles and "anaesthetist" in roles
    for name, tr in roles.items():
        assert [round(k.time_s, 3) for k in tr.keyframes] == [2.0, 2.05, 2.1, 2.15, 2.2]
        for k in tr.keyframes:
            truth = world.head_poses(k.time_s)[name]  # eval-set sessions: case time = sim time
            pose = k.pose()
            assert np.allclose(pose.centre_m, truth.centre_m, atol=2e-6)
            assert np.allclose(pose.R, truth.R, atol=1e-5)
    boxes = read_site(case["site"])
    assert {"monitor-a", "monitor-b"} <= set(boxes)


def test_a_path_passes_through_its_keyframes_and_turns_smoothly_between(tmp_path):
    a = Pose.look_at(np.array([0.0, 0.0, 1.6]), np.array([1.0, 0.0, 1.6]))
    b = Pose.look_at(np.array([1.0, 1.0, 1.6]), np.array([1.0, 2.0, 1.6]))
    keys = (Keyframe.from_pose(0.0, a, 80), Keyframe.from_pose(2.0, b, 100))
    path_file = write_trajectories(tmp_path / "t.toml", [Trajectory(name="walk", keyframes=keys)])
    path = CameraPath(read_trajectories(path_file)[0])
    assert np.allclose(path.pose(0.0).matrix, a.matrix, atol=1e-5)
    assert np.allclose(path.pose(2.0).matrix, b.matrix, atol=1e-5)
    mid = path.pose(1.0)
    # halfway through a 90 degree turn about +z: looking along (1, 1, 0) / sqrt 2
    assert np.allclose(mid.R[2], [np.sqrt(0.5), np.sqrt(0.5), 0.0], atol=1e-6)
    assert path.fov_deg(1.0) == pytest.approx(90.0)


def test_replay_writes_an_h264_mp4_with_the_model_of_each_instant(case, capsys, tmp_path):
    out = tmp_path / "surgeon.mp4"
    done = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles",
                       str(case["roles"]), "--out", str(out), "--fps", "20", "--size", "160x100",
                       "--pip")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        assert stream.codec_context.name == "h264"
    assert len(frames) == 5 and frames[0].shape == (100, 160, 3)  # 2.0 .. 2.2 s at 20 fps
    # the burned-in time code's band: dark with white text, at the top left of every frame
    assert all(f[2:10, 2:40].max() > 200 and f[2:10, 2:40].min() < 40 for f in frames)


def test_the_model_shown_is_the_last_one_at_or_before_each_instant_and_preload_gives_the_same(
    case,
):
    models = CaseModels(case["case"])
    names = [models.entry_at(t).name for t in (2.0, 2.05, 2.0667, 2.1, 2.2)]
    assert names == ["t00002.000", "t00002.000", "t00002.067", "t00002.067", "t00002.133"]
    order = [models.entry_at(t) for t in np.arange(2.0, 2.2, 0.02)]
    with (
        ModelSource(models, order, preload=True) as pre,
        ModelSource(models, order, preload=False) as plain,
    ):
        for e in order:
            assert np.array_equal(pre.get(e).means_m.numpy(), plain.get(e).means_m.numpy())


def test_a_damaged_model_is_refused_by_its_checksum(case, capsys, tmp_path):
    import shutil

    copy = tmp_path / "case"
    shutil.copytree(case["case"], copy)
    index = json.loads((copy / "case.json").read_text())
    victim = copy / index["timestamps"][1]["model"]
    blob = bytearray(victim.read_bytes())
    blob[-3] ^= 0xFF
    victim.write_bytes(bytes(blob))
    done = egosurg(capsys, "replay", str(copy), "--role", "surgeon", "--roles", str(case["roles"]),
                       "--out", str(tmp_path / "x.mp4"), "--size", "64x40")  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "fails its checksum" in done.stderr
    assert not (tmp_path / "x.mp4").exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--role", "janitor"), "no role 'janitor'"),
        (("--role", "surgeon", "--from", "1.0"), "outside trajectory"),
        (("--role", "surgeon", "--size", "97x60"), "even sides"),
        ((), "holds 6 trajectories"),
    ],
)
def test_bad_replay_input_gets_one_clear_line(case, capsys, tmp_path, extra, message):
    done = egosurg(capsys, "replay", str(case["case"]), "--roles", str(case["roles"]),
                       "--out", str(tmp_path / "x.mp4"), *extra)  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert message in done.stderr


def test_sightline_writes_the_csv_the_timeline_and_the_worst_instants(case, capsys, tmp_path):
    out = tmp_path / "los"
    done = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                       str(case["roles"]), "--target", "monitor-b", "--site", str(case["site"]),
                       "--offset", "1m left-posterior", "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader((out / "sightline.csv").open()))
    assert [r["position"] for r in rows] == ["actual", "1m left-posterior"] * 3
    assert all(0.0 <= float(r["visible_fraction"]) <= 1.0 for r in rows)
    for a, b in zip(rows[::2], rows[1::2], strict=True):  # the offset is 1 m, horizontal
        d = np.subtract([float(b[k]) for k in ("eye_x_m", "eye_y_m", "eye_z_m")],
                        [float(a[k]) for k in ("eye_x_m", "eye_y_m", "eye_z_m")])  # fmt: skip
        assert np.linalg.norm(d) == pytest.approx(1.0, abs=2e-3) and abs(d[2]) < 1e-3
    assert (out / "timeline.png").stat().st_size > 5000
    assert len(list(out.glob("worst_*.png"))) == 2
    bad = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                      str(case["roles"]), "--target", "xray", "--site", str(case["site"]),
                      "--out", str(out))  # fmt: skip
    assert bad.returncode == 2 and "no target 'xray'" in bad.stderr


def _flip_left_images(session: Path, only: tuple[int, int] | None = None) -> list[str]:
    """One byte changed in the middle of every camera's left images, or ``only`` the one of
    (serial, row): "SN<serial> row <r> left" of each."""
    import h5py

    damaged = []
    with h5py.File(session, "r+") as f:
        for name in f["cameras"]:
            g = f[f"cameras/{name}"]
            for row in range(g["left_offset"].shape[0]):
                if only is not None and only != (int(name), row):
                    continue
                off, n = int(g["left_offset"][row]), int(g["left_length"][row])
                g["left_bytes"][off + n // 2] ^= 0x01
                damaged.append(f"SN{name} row {row} left")
    return damaged


def test_replay_pip_shows_a_damaged_real_frame_as_damaged_and_lists_it(case, capsys, tmp_path):
    import shutil

    session = tmp_path / "session.h5"
    shutil.copy(case["session"], session)
    damaged = _flip_left_images(session)
    copy = tmp_path / "case"
    shutil.copytree(case["case"], copy)
    index = json.loads((copy / "case.json").read_text())
    index["session"] = str(session)
    (copy / "case.json").write_text(json.dumps(index))
    out = tmp_path / "pip.mp4"
    done = egosurg(capsys, "replay", str(copy), "--role", "surgeon", "--roles",
                   str(case["roles"]), "--out", str(out), "--size", "160x100", "--pip")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "damaged real frame(s) not shown (checksum mismatch)" in done.stderr, done.stderr
    named = done.stderr.rsplit("checksum mismatch): ", 1)[1].strip().split(", ")
    assert named and set(named) <= set(damaged)
    assert out.stat().st_size > 0  # the replay itself is whole


def test_reconstruct_leaves_out_a_damaged_view_names_it_and_records_it(case, tmp_path):
    import shutil

    folder = tmp_path / "session"
    shutil.copytree(case["session"].parent, folder)
    from protocol.session import SessionReader

    with SessionReader(folder / "session.h5") as reader:  # the first camera's frame in set 0
        serial, row = reader.info.camera_serials[0], int(reader.sets().members[0, 0])
    (damaged,) = _flip_left_images(folder / "session.h5", only=(serial, row))
    out = tmp_path / "out"
    done = run_egosurg("reconstruct", str(folder / "session.h5"), "--config",
                       str(case["root"] / "tiny.toml"), "--at", "set:0", "--out", str(out),
                       timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"{damaged} image is damaged (checksum mismatch)" in done.stderr, done.stderr
    (summary_path,) = out.glob("*/summary.json")
    summary = json.loads(summary_path.read_text())
    assert summary["damaged_images"] == [damaged]
    assert not any(name.startswith(f"SN{serial}-") for name in summary["sensors"])
