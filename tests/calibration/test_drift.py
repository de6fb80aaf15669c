"""The drift check's alignment: a camera that moved must not drag the cameras that stayed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.solve.drift import align_to
from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration
from sim import World
from sim.truth import true_rig_calibration
from tests.helpers import moved_camera


@pytest.fixture(scope="module")
def rig() -> RigCalibration:
    return true_rig_calibration(World.from_seed(5, phase="wand"))


def _in_another_frame(cal: RigCalibration, seed: int) -> RigCalibration:
    """``cal`` in a world turned and shifted at random: what a second solve of the rig returns."""
    rng = np.random.default_rng(seed)
    frame = Pose(R=Rotation.random(random_state=seed).as_matrix(), t_m=rng.normal(0, 2.0, 3))
    return replace(
        cal, sensors=tuple(replace(s, pose=s.pose.compose(frame.inverse())) for s in cal.sensors)
    )


def _noisy(cal: RigCalibration, sd_m: float, seed: int) -> RigCalibration:
    rng = np.random.default_rng(seed)
    return replace(
        cal,
        sensors=tuple(
            replace(s, pose=Pose(R=s.pose.R, t_m=s.pose.t_m + rng.normal(0, sd_m, 3)))
            for s in cal.sensors
        ),
    )


def test_an_unchanged_rig_shows_no_drift_in_any_frame(rig):
    drift = align_to(_in_another_frame(rig, 1), rig)
    assert drift.position_mm.max() < 1e-6 and drift.rotation_deg.max() < 1e-6
    assert len(drift.fitted_serials) == len({s.camera_serial for s in rig.sensors})
    assert drift.aligned.world_frame == rig.world_frame


@pytest.mark.parametrize("which", [0, 2, 4, 6])
def test_one_moved_camera_carries_the_whole_drift(rig, which):
    """12 mm on one camera of four, with 1 mm of solve noise everywhere: a least-squares fit over
    all cameras would show about 3 mm on each camera that stayed; the others must stay within
    the noise and the moved camera must show the whole move."""
    serial = rig.sensors[which].camera_serial
    old = moved_camera(rig, serial, np.array([0.012, 0.0, 0.0]))
    new = _in_another_frame(_noisy(rig, 0.001, which), 7)
    drift = align_to(new, old, outlier_mm=5.0)
    for s, mm in zip(drift.aligned.sensors, drift.position_mm, strict=True):
        if s.camera_serial == serial:
            assert 9.0 < mm < 15.0, (s.name, mm)
        else:
            assert mm < 3.0, (s.name, mm)
    assert serial not in drift.fitted_serials
    assert drift.rotation_deg.max() < 0.1


def test_half_the_rig_moved_is_not_guessed_at(rig):
    """Two of four cameras moved the same way: no majority agrees, so nothing is left out and
    the drift shows on the rig as a whole rather than on a guessed half."""
    serials = list(dict.fromkeys(s.camera_serial for s in rig.sensors))
    old = rig
    for serial in serials[:2]:
        old = moved_camera(old, serial, np.array([0.0, 0.03, 0.0]))
    drift = align_to(_in_another_frame(rig, 3), old, outlier_mm=5.0)
    assert len(drift.fitted_serials) >= 3
    assert (drift.position_mm > 5.0).sum() >= 2
