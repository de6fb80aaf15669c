"""Evaluation sets: ``egosurg sim eval-set`` writes scenes a reconstructor reads through protocol/,
and the reference views are the sim's exact egocentric views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.eval_set import EvalSet, EvalSetError
from protocol.images import decode_image
from protocol.rig_calibration import RigCalibration
from protocol.session import SessionReader
from sim import World
from sim.timing import SIM_EPOCH_UNIX_NS
from tests.conftest import run_egosurg

SEED = 3


@pytest.fixture(scope="module")
def eval_set(tmp_path_factory) -> EvalSet:
    out = tmp_path_factory.mktemp("evalset")
    r = run_egosurg(
        "sim", "eval-set", "--out", str(out), "--seed", str(SEED), "--phases", "intraoperative",
        "--sets", "3", "--eval-sets", "0,2", "--view-size", "160x100",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "1 scenes" in r.stdout
    return EvalSet.read(out)


def test_the_session_holds_consecutive_sets_of_every_camera_at_sim_time(eval_set):
    scene = eval_set.scenes[0]
    world = World.from_seed(SEED, phase="intraoperative")
    with SessionReader(eval_set.path(scene.session)) as reader:
        sets = reader.sets()
        assert len(sets.set_unix_ns) == 3 == len(scene.temporal_sets)
        assert not (sets.members < 0).any()
        t_s = (sets.set_unix_ns - reader.info.started_unix_ns) / 1e9
        np.testing.assert_allclose(t_s, [2.0, 2.0 + 1 / 15, 2.0 + 2 / 15], atol=1e-9)
        assert reader.info.started_unix_ns == SIM_EPOCH_UNIX_NS
        serial = reader.info.camera_serials[1]
        cam = reader.info.camera(serial)
        left, _ = reader.frame_bytes(serial, int(sets.members[2, 1]))
        stored = decode_image(left, cam.encoding, cam.width, cam.height)[:, :, ::-1]
    truth = world.render_sensor(world.unit_by_serial(serial), "left", float(t_s[2]), "SVGA")
    other = world.render_sensor(world.unit_by_serial(serial), "right", float(t_s[2]), "SVGA")
    # the stored frame is the sim's sensor image at that instant, through JPEG (q90) only
    err = np.abs(stored.astype(float) - truth.image_rgb.astype(float)).mean()
    err_other = np.abs(stored.astype(float) - other.image_rgb.astype(float)).mean()
    assert err < 3.0 and err_other > 3 * err


def test_reference_views_are_the_people_s_eyes_at_the_set_s_instant(eval_set):
    scene = eval_set.scenes[0]
    world = World.from_seed(SEED, phase="intraoperative")
    calibration = RigCalibration.read(eval_set.path(scene.calibration))
    assert len(calibration.sensors) == 8
    for k in (0, 2):
        views = scene.views_at(k)
        poses = world.head_poses(2.0 + k / 15)
        assert {v.role for v in views} == set(poses)
        for v in views:
            np.testing.assert_allclose(v.camera.pose.R, poses[v.role].R, atol=1e-12)
            np.testing.assert_allclose(v.camera.pose.t_m, poses[v.role].t_m, atol=1e-12)
    v = scene.views_at(2)[0]
    image = eval_set.image(v)
    assert image.shape == (100, 160, 3)
    truth = world.render(v.camera, 2.0 + 2 / 15).image_rgb
    assert np.array_equal(image, truth)  # PNG: lossless


def test_bad_sets_are_named(tmp_path, eval_set):
    with pytest.raises(EvalSetError, match="egosurg sim eval-set"):
        EvalSet.read(tmp_path)
    text = (eval_set.root / "eval_set.toml").read_text()
    (tmp_path / "eval_set.toml").write_text(
        text.replace("format_version = 1", "format_version = 9")
    )
    with pytest.raises(EvalSetError, match="format_version 9"):
        EvalSet.read(tmp_path)
    (tmp_path / "eval_set.toml").write_text(text)  # its sessions are not beside this copy
    with pytest.raises(EvalSetError, match=r"intraoperative/session\.h5, which is missing"):
        EvalSet.read(tmp_path)


def test_bad_arguments_get_one_line(tmp_path: Path):
    r = run_egosurg("sim", "eval-set", "--out", str(tmp_path), "--phases", "wand")
    assert r.returncode == 2
    assert "choose from empty, setup, intraoperative, turnover" in r.stderr
    assert "Traceback" not in r.stderr
