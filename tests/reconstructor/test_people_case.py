"""``egosurg people`` end to end on a reconstructed sim case: 12 timestamps at 2 Hz of the
intraoperative phase (six people), reconstructed with a tiny training config (stereo at half
scale, as fine as heads need: what the case stores is what people are found in, no stereo run
again), people found (the empty room recorded by the same rig as the background) with the
``sim`` package made unimportable (the command must not lean on the simulator's truth), then
judged against ``World.head_poses`` as bench/bench_people.py judges a whole phase."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.formats.trajectory import read_trajectory_file

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
NO_SIM = (
    "import sys; sys.modules['sim'] = None\n"  # any 'import sim...' now raises ImportError
    "from protocol.cli import main\n"
    "raise SystemExit(main(sys.argv[1:]))\n"
)


@pytest.fixture(scope="module")
def people_case(tmp_path_factory):
    from reconstructor.cli import main_reconstruct
    from sim.eval_set import EvalSetSpec, write_eval_set
    from tests.reconstructor.tiny import tiny_config_toml

    root = tmp_path_factory.mktemp("people")
    # 6 s is too short to learn the room from (the surgeon stands still through it): the empty
    # room, recorded by the same rig, is the background, as docs/replay.md says for short spans
    spec = EvalSetSpec(phases=("empty", "intraoperative"), fps=2.0, sets=12, instants=1,
                       view_size_px=(64, 40))  # fmt: skip
    write_eval_set(root / "es", spec)
    session = root / "es" / "intraoperative" / "session.h5"
    config = root / "tiny.toml"
    # the tiny config's quarter-scale stereo is too thin for heads (the command would read the
    # session instead): the case matches at half scale, so its stored evidence is read
    config.write_text(tiny_config_toml(3).replace("match_scale = 0.25", "match_scale = 0.5"))
    code = main_reconstruct([str(session), "--every", "0.5s", "--out", str(root / "case"),
                             "--config", str(config), "--cold"])  # fmt: skip
    assert code == 0
    out = root / "people.toml"
    run = subprocess.run(
        [sys.executable, "-c", NO_SIM, "people", str(root / "case"), "--out", str(out),
         "--background", str(root / "es" / "empty" / "session.h5")],
        cwd=REPO, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    return root, out, run


def test_the_command_runs_without_the_simulator_and_writes_the_people_file(people_case):
    _, out, run = people_case
    assert run.returncode == 0, run.stderr[-2000:]
    assert "tracks over 12 timestamps" in run.stdout
    assert "12 timestamps (case evidence)" in run.stderr  # the case's own cells, no stereo
    file = read_trajectory_file(out)
    assert file.session is not None and file.session.name  # the case's session, recorded
    assert len(file.trajectories) >= 4


def test_heads_against_the_simulators_truth(people_case):
    """The goal is an eye position median <= 10 cm; it is not met yet (EVALUATION.md, "People
    from the recording": 10-13 cm per phase, mostly a facing turned round, which puts the eye
    26 cm behind the head). Each person is matched within 0.5 m at each timestamp; bound: the
    median of all matches within 15 cm (measured here: 13.8 cm), and at least five of the six
    people matched at half the timestamps or more (measured: five, at 6-12 of 12; the surgeon,
    standing still at the table, at 5)."""
    from bench.bench_people import score
    from protocol.formats.rig_calibration import RigCalibration
    from reconstructor.people.config import PeopleConfig
    from reconstructor.people.run import find_people
    from reconstructor.people.sources import open_source
    from sim.world import World

    root, _, _ = people_case
    source = open_source(root / "case")
    empty = open_source(root / "es" / "empty" / "session.h5", every_s=1.0)
    people = find_people(source, PeopleConfig(), background=empty)
    rig = RigCalibration.read(root / "case" / "calibration.toml")
    centres = np.array([s.camera.pose.centre_m for s in rig.sensors if s.side == "left"])
    world = World.from_seed(3, phase="intraoperative")
    scores = score(world, people, PeopleConfig(), centres, 6.0)
    errors = [e for s in scores.values() for e in s.pos_err_m]
    assert np.median(errors) <= 0.15, np.median(errors)
    matched = [n for n, s in scores.items() if len(s.pos_err_m) >= 6]
    assert len(matched) >= 5, {n: len(s.pos_err_m) for n, s in scores.items()}
