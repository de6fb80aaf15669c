"""Shared fixtures. Worlds are expensive to build (textures, rig), so tests share them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def world():
    from sim import World

    return World.from_seed(11, phase="intraoperative")


@pytest.fixture(scope="session")
def wand_world():
    from sim import World

    return World.from_seed(5, phase="wand")


def run_egosurg(*args: str, timeout: float = 300.0, cwd: Path | None = None):
    """Run the real ``egosurg`` command in a subprocess, as a user would."""
    env = dict(os.environ)
    return subprocess.run(
        [sys.executable, "-m", "protocol.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd or REPO,
        env=env,
    )


@pytest.fixture(scope="session")
def sim_true_rig():
    """The simulator's true rig as a calibration: 4 ZED X, 8 sensors, lenses with k3 != 0."""
    from sim import World
    from sim.truth import true_rig_calibration

    return true_rig_calibration(World.from_seed(0))
