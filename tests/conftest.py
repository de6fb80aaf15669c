"""Shared fixtures. Worlds are expensive to build (textures, rig), so tests share them."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, settings

# capture tests import run_egosurg from here; the other tests from tests.helpers
from tests.helpers import REPO, run_egosurg  # noqa: F401

# Property tests run on 2 shared cores beside real processes: a slow draw is the machine, not the
# code (no deadlines, no too-slow health check), and the same examples run every time, so a
# failure in CI reproduces here (derandomize; no example database in the checkout).
settings.register_profile(
    "egosurg",
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("egosurg")


@pytest.fixture(scope="session")
def world():
    from sim import World

    return World.from_seed(11, phase="intraoperative")


@pytest.fixture(scope="session")
def wand_world():
    from sim import World

    return World.from_seed(5, phase="wand")


@pytest.fixture(scope="session")
def sim_true_rig():
    """The simulator's true rig as a calibration: 4 ZED X, 8 sensors, lenses with k3 != 0, one
    of them on the rational model (k4..k6, ``sim.rig.RATIONAL_SENSOR``)."""
    from sim import World
    from sim.truth import true_rig_calibration

    return true_rig_calibration(World.from_seed(0))
