"""Evaluation sets: ``egosurg sim eval-set`` writes scenes a reconstructor reads through protocol/,
and the reference views are the sim's exact egocentric views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.formats.eval_set import EvalSet, EvalSetError
from protocol.formats.rig_calibration import RigCalibration
from protocol.images import decode_image
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
        "--sets", "3", "--eval-sets", "0,2", "--view-size", "160x100", "--instants", "1",
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


def test_later_instants_are_a_second_scene_of_the_phase_with_every_person_s_view(tmp_path):
    """Egocentric statistics over one instant are statistics over one arrangement of the room:
    the later instants are seconds apart, each with every person's view; the first ones are
    near-field instants too."""
    r = run_egosurg(
        "sim", "eval-set", "--out", str(tmp_path), "--phases", "turnover", "--sets", "2",
        "--instants", "3", "--instant-every", "2.5", "--near-field-instants", "2",
        "--view-size", "32x20",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    es = EvalSet.read(tmp_path)
    main, later = es.scenes
    assert (main.name, later.name) == ("turnover", "turnover-later")
    assert main.phase == later.phase == "turnover"
    assert later.eval_sets == (0,) and later.temporal_sets == ()  # 2 near-field instants in all
    world = World.from_seed(SEED, phase="turnover")
    with SessionReader(es.path(later.session)) as reader:
        sets = reader.sets()
        t_s = (sets.set_unix_ns - reader.info.started_unix_ns) / 1e9
    np.testing.assert_allclose(t_s, [4.5, 7.0], atol=1e-9)  # t = 2 + 2.5 k, k = 1, 2
    for k, t in enumerate(t_s):
        poses = world.head_poses(float(t))
        assert {v.role for v in later.views_at(k)} == set(poses)
        for v in later.views_at(k):
            np.testing.assert_allclose(v.camera.pose.t_m, poses[v.role].t_m, atol=1e-12)
    # the people moved between the instants: no view repeats another instant's
    first = {v.role: v.camera.pose.t_m for v in main.views_at(0)}
    moved = [np.linalg.norm(v.camera.pose.t_m - first[v.role]) for v in later.views_at(1)]
    assert max(moved) > 0.1, moved
    assert "3 instants 2.5 s apart" in es.description
    assert "--instants 3 --instant-every 2.5 --near-field-instants 2" in es.description


def test_the_default_set_is_the_paper_s_scale():
    """Every phase, at least 10 instants over the phases, 60+ egocentric views and at
    least 3 near-field instants per phase, by default (counted without rendering)."""
    from sim.eval_set import EvalSetSpec

    spec = EvalSetSpec()
    assert set(spec.phases) == {"empty", "setup", "intraoperative", "turnover"}
    assert spec.sets >= 10 and spec.near_field_instants >= 3
    views = instants = 0
    for phase in spec.phases:
        world = World.from_seed(spec.seed, phase=phase)
        for t in (spec.t_start_s, *spec.later_instants_s):
            people = len(world.head_poses(t))
            views += people
            instants += people > 0
    assert instants >= 10 and views >= 60, (instants, views)


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--instants", "0"], ["instants=0", "at least 1"]),
        (["--sets", "30", "--instant-every", "1"], ["instant_every_s=1", "--instants 1"]),
        (["--near-field-instants", "0"], ["near_field_instants=0", "at least 1"]),
    ],
)
def test_bad_instants_get_one_line(extra, words, tmp_path):
    r = run_egosurg("sim", "eval-set", "--out", str(tmp_path), "--phases", "setup", *extra)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and all(w in line for w in words), line
