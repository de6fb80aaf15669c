"""A whole case through the real ``egosurg reconstruct --every`` and ``egosurg case`` commands:
the folder and its index, resume after SIGKILL, bad inputs. Reconstructions are tiny (96 px
wide, a few steps, stereo at quarter scale) so a timestamp takes well under a second."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xxhash

from reconstructor.case import storage
from reconstructor.case.index import CaseIndex
from reconstructor.splats import ply
from tests.helpers import REPO, run_egosurg
from tests.reconstructor.tiny import tiny_config_toml


def _index(folder: Path) -> dict:
    return json.loads((folder / "case.json").read_text())


def _xxh(path: Path) -> str:
    return xxhash.xxh3_64(path.read_bytes()).hexdigest()


def _args(session: Path, config: Path, out: Path, *extra: str) -> list[str]:
    return ["reconstruct", str(session), "--config", str(config), "--out", str(out), *extra]


@pytest.mark.slow  # about 45 s on 2 loaded cores: five runs of the command
def test_a_case_holds_one_checked_model_per_timestamp_and_a_rerun_skips_them(
    tiny_session, tmp_path
):
    h5, config = tiny_session
    out = tmp_path / "case"
    done = run_egosurg(*_args(h5, config, out, "--every", "0.1s", "--cold"), timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = _index(out)["timestamps"]
    assert not _index(out)["warm_start"]
    # 2.0 .. 2.3 s every 0.1 s, each at its nearest set
    assert [r["set_index"] for r in rows] in ([0, 1, 3, 4], [0, 2, 3, 4], [0, 1, 3, 5])
    assert all(r["status"] == "done" for r in rows)
    for r in rows:
        path = out / r["model"]
        assert _xxh(path) == r["xxh3_64"] and path.stat().st_size == r["bytes"]
    for e in CaseIndex.read(out).timestamps:  # what the stereo saw, for the sterile tool
        points = storage.load_points(out, e)
        assert points is not None and len(points) > 1000 and np.isfinite(points).all()
    stamps = {r["name"]: (out / r["model"]).stat().st_mtime_ns for r in rows}

    # a damaged model is found by its checksum and redone; the others are skipped
    victim = out / rows[1]["model"]
    blob = bytearray(victim.read_bytes())
    blob[-5] ^= 0xFF
    victim.write_bytes(bytes(blob))
    again = run_egosurg(*_args(h5, config, out, "--every", "0.1s", "--cold"), timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    after = {r["name"]: (out / r["model"]).stat().st_mtime_ns for r in _index(out)["timestamps"]}
    changed = [n for n in stamps if after[n] != stamps[n]]
    assert changed == [rows[1]["name"]]
    assert _xxh(victim) == _index(out)["timestamps"][1]["xxh3_64"]

    info = run_egosurg("case", "info", str(out))
    assert info.returncode == 0 and "4 done, 0 pending, 0 failed" in info.stdout
    # a cold case is stored compactly too: each timestamp a quantised keyframe
    assert "storage: 4 compact" in info.stdout and "0 full PLY" in info.stdout, info.stdout

    exported = tmp_path / "export"
    exp = run_egosurg("case", "export", str(out), "--out", str(exported))
    assert exp.returncode == 0, exp.stderr
    for r in rows:
        # exported models carry unit quaternions (training leaves them at 0.74-1.06)
        g = ply.read_ply(exported / f"{r['name']}.ply")
        assert np.allclose(np.linalg.norm(g.quats_wxyz.numpy(), axis=1), 1.0, atol=1e-5)

    # other settings in the same folder are refused, and nothing finished is touched
    other = tmp_path / "other.toml"
    other.write_text(tiny_config_toml(4))
    refused = run_egosurg(*_args(h5, other, out, "--every", "0.1s", "--cold"))
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert "other settings" in refused.stderr and "--force" in refused.stderr
    assert {
        r["name"]: (out / r["model"]).stat().st_mtime_ns for r in _index(out)["timestamps"]
    } == after


@pytest.mark.slow  # about 60 s on 2 loaded cores
def test_a_run_killed_halfway_resumes_and_the_index_never_names_a_partial_file(
    tiny_session, tmp_path
):
    h5, _ = tiny_session
    config = tmp_path / "slower.toml"
    config.write_text(tiny_config_toml(40))  # long enough to be caught halfway
    out = tmp_path / "case"
    argv = [sys.executable, "-m", "protocol.cli", *_args(h5, config, out, "--every", "0.0667s")]
    proc = subprocess.Popen(
        argv, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True,
    )  # fmt: skip
    deadline = time.monotonic() + 240
    seen_done = 0
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / "case.json").exists():
                rows = _index(out)["timestamps"]  # replaced atomically: always whole JSON
                for r in rows:
                    if r["status"] == "done":  # what the index names is whole, at any moment
                        assert _xxh(out / r["model"]) == r["xxh3_64"]
                seen_done = sum(r["status"] == "done" for r in rows)
                if seen_done >= 1:
                    break
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    planned = len(_index(out)["timestamps"])  # the index lists every timestamp from the start
    assert 1 <= seen_done < planned, "the run finished before it could be killed halfway"
    before = {r["name"]: r for r in _index(out)["timestamps"] if r["status"] == "done"}
    for r in before.values():
        assert _xxh(out / r["model"]) == r["xxh3_64"]
    stamps = {n: (out / r["model"]).stat().st_mtime_ns for n, r in before.items()}

    done = run_egosurg(*_args(h5, config, out, "--every", "0.0667s"), timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = _index(out)["timestamps"]
    assert len(rows) == planned and all(r["status"] == "done" for r in rows)
    for n, mtime in stamps.items():  # finished work is kept, not redone
        assert (out / before[n]["model"]).stat().st_mtime_ns == mtime
    assert not list(out.rglob("*.partial")) and not any((out / ".work").iterdir())


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--every", "0.01s"), "shorter than the session's frame period"),
        (("--every", "1s", "--from", "30"), "outside the session"),
        (("--every", "1s", "--to", "-4"), "outside the session"),
        (("--every", "often"), "write a duration"),
        (("--every", "1s", "--ray", "127.0.0.1:1"), "does not answer"),
        (("--every", "1s", "--at", "2.0"), "not both"),
        (("--every", "1s", "--cold", "--warm-steps", "5"), "--cold turns off"),
        (("--every", "1s", "--cold", "--warm-start"), "not allowed with argument"),
    ],
)
def test_bad_case_options_get_one_clear_line(tiny_session, tmp_path, extra, message):
    h5, config = tiny_session
    done = run_egosurg(*_args(h5, config, tmp_path / "case", *extra), timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert message in done.stderr


def test_a_folder_that_is_not_a_case_is_refused_untouched(tiny_session, tmp_path):
    h5, config = tiny_session
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "holiday.jpg").write_bytes(b"jpeg")
    done = run_egosurg(*_args(h5, config, foreign, "--every", "1s"))
    assert done.returncode == 2 and "not a case folder" in done.stderr
    assert sorted(p.name for p in foreign.iterdir()) == ["holiday.jpg"]
    info = run_egosurg("case", "info", str(foreign))
    assert info.returncode == 2 and "not a case folder" in info.stderr


@pytest.mark.slow  # about 20 s on 2 loaded cores
def test_warm_start_chains_each_timestamp_to_the_one_before_and_keyframes_start_cold(
    tiny_session, tmp_path
):
    h5, config = tiny_session
    out = tmp_path / "case"
    extra = ("--every", "0.1s", "--warm-start", "--warm-steps", "2", "--keyframe-every", "3")
    done = run_egosurg(*_args(h5, config, out, *extra), timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    index = _index(out)
    rows = index["timestamps"]
    assert index["warm_start"] and [r["chain"] for r in rows] == [0, 0, 0, 1]
    assert [r["warm_from"] for r in rows] == ["", rows[0]["name"], rows[1]["name"], ""]
    assert (out / "config_warm.toml").exists()
    # a cold run of the same times is other settings: refused in this folder
    cold = run_egosurg(*_args(h5, config, out, "--every", "0.1s", "--cold"))
    assert cold.returncode == 2 and "other settings" in cold.stderr
    # warm start is the default: the same command without --warm-start is the same case
    again = run_egosurg(*_args(h5, config, out, "--every", "0.1s", "--warm-steps", "2",
                               "--keyframe-every", "3"))  # fmt: skip
    assert again.returncode == 0 and "4 done" in again.stdout, again.stderr[-2000:]


def _splats(means_m, log_scales, quats_wxyz, opacity):
    import torch

    from reconstructor.splats.gaussians import Gaussians

    n = len(means_m)
    return Gaussians(
        means_m=torch.tensor(means_m, dtype=torch.float32),
        quats_wxyz=torch.tensor(quats_wxyz, dtype=torch.float32),
        log_scales=torch.tensor(log_scales, dtype=torch.float32),
        opacity_logits=torch.logit(torch.tensor(opacity, dtype=torch.float64)).float(),
        sh_dc=torch.zeros(n, 3),
        sh_rest=torch.zeros(n, 0, 3),
    )


def _no_cameras():
    """A timestamp at which every camera is missing: nothing is seen, so nothing is in free
    space, and the warm start's other rules act alone."""
    from protocol.camera import Resolution
    from reconstructor.data.frames import Timestamp

    return Timestamp(Path("x.h5"), 0, 0, 0.0, (), (), Resolution.parse("SVGA"))


def test_a_warm_start_drops_splats_too_faint_to_draw_and_names_the_rows_it_kept():
    """A user's warm model does not carry splats that draw nothing (opacity below the
    rasterizer's 1/255 cut-off) into every later step, and compact storage learns which of the
    previous rows survive."""
    from reconstructor.case.warm import WarmStartConfig, seed_from_previous
    from reconstructor.depth.fusion import FusedCloud
    from reconstructor.splats.gaussians import GaussianInitConfig

    means = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]]
    previous = _splats(means, np.log(np.full((3, 3), 0.05)), [[1.0, 0, 0, 0]] * 3,
                       [0.5, 1 / 1000, 0.02])  # fmt: skip
    fused = FusedCloud(np.asarray(means, np.float32), np.full((3, 3), 0.5, np.float32))
    seed = seed_from_previous(previous, _no_cameras(), fused, {}, WarmStartConfig(),
                              GaussianInitConfig())  # fmt: skip
    assert seed.alive.tolist() == [True, False, True]
    assert seed.counts == {"kept": 2, "dropped": 0, "faded": 1, "added": 0}
    assert seed.gaussians.means_m[:, 0].tolist() == [0.0, 2.0]


def test_a_point_inside_a_flat_splat_is_covered_and_one_in_front_of_it_is_new_content():
    """A wall seen again is not seeded again (its new stereo points fall inside the trained
    splats, though centimetres from their centres), yet a hand 8 cm in front of the wall is."""
    from reconstructor.case.warm import WarmStartConfig, uncovered

    # one flat splat at the origin, 10 x 10 cm across and 2 mm thick, turned 90 degrees about
    # x: its thin axis is the world's y axis, its broad ones x and z
    half = np.sqrt(0.5)
    wall = _splats([[0.0, 0.0, 0.0]], np.log([[0.1, 0.1, 0.002]]), [[half, half, 0, 0]], [0.9])
    points = np.array(
        [
            [0.08, 0.0, 0.0],  # 8 cm across the wall: 0.8 sd
            [0.0, 0.0, 0.08],  # 8 cm across the wall the other way
            [0.0, 0.08, 0.0],  # 8 cm in front of it: 40 sd
            [0.0, 0.01, 0.0],  # 1 cm in front: stereo noise, nearer than new_point_distance_m
            [0.5, 0.0, 0.0],  # 50 cm along: beyond the splat (5 sd)
        ]
    )
    cfg = WarmStartConfig(new_point_distance_m=0.03, cover_sigmas=3.0)
    assert uncovered(points, wall, cfg).tolist() == [False, False, True, False, True]
    # in metres alone (the rule before cover_sigmas), the wall's own points were new
    metres_only = WarmStartConfig(new_point_distance_m=0.03, cover_sigmas=0.0)
    assert uncovered(points, wall, metres_only).tolist() == [True, True, True, False, True]
