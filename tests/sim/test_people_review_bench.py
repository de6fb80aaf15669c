"""bench/bench_people_review.py's naming and coverage: the estimated roles a reviewer would get
from ``egosurg people`` named by the sim's truth, and the instants they answer at."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.bench_people_review import estimated_pose, los_scores, name_people
from protocol.formats.session_id import SessionId
from protocol.formats.trajectory import (
    Keyframe,
    Trajectory,
    read_trajectory_file,
    write_trajectories,
)
from reconstructor.replay.path import CameraPath
from sim.world import World

TIMES_S = (2.0, 2.5, 3.0)


@pytest.fixture(scope="module")
def world():
    return World.from_seed(3, phase="intraoperative")


def _track(world, name, person, shift_m):
    keys = []
    for t in TIMES_S:
        pose = world.head_poses(t)[person]
        k = Keyframe.from_pose(t, pose, 90.0)
        keys.append(dataclasses.replace(k, eye_m=tuple(np.add(k.eye_m, shift_m))))
    return Trajectory(name=name, keyframes=tuple(keys))


def test_tracks_are_named_after_the_nearest_true_eye_and_keep_their_estimated_keyframes(
    world, tmp_path
):
    """Each track near a person takes that person's name, a track 1 m from everyone none, and the
    roles file holds the track's own (estimated) eyes and the people file's session."""
    session = SessionId(name="sim-intraoperative-seed3", started_unix_ns=1767225600000000000)
    people = tmp_path / "people.toml"
    tracks = [
        _track(world, "track1", "surgeon", (0.12, 0.0, 0.0)),
        _track(world, "track2", "anaesthetist", (0.0, -0.2, 0.05)),
        _track(world, "track3", "circulator", (1.0, 0.0, 0.0)),
    ]
    write_trajectories(people, tracks, session)
    roles = tmp_path / "roles.toml"
    named = {n.track: n.role for n in name_people(people, world, roles)}
    assert named == {"track1": "surgeon", "track2": "anaesthetist"}
    written = read_trajectory_file(roles)
    assert written.session == session
    surgeon = {t.name: t for t in written.trajectories}["surgeon"]
    true_eye = world.head_poses(2.0)["surgeon"].centre_m
    assert np.linalg.norm(np.subtract(surgeon.keyframes[0].eye_m, true_eye)) == pytest.approx(
        0.12, abs=1e-5
    )


def test_a_role_answers_only_inside_its_track_and_an_unnamed_person_never(world):
    paths = {"surgeon": CameraPath(_track(world, "surgeon", "surgeon", (0.0, 0.0, 0.0)))}
    assert estimated_pose(paths, "surgeon", 2.5) is not None
    assert estimated_pose(paths, "surgeon", 3.5) is None  # after the track's last keyframe
    assert estimated_pose(paths, "assistant", 2.5) is None  # no track named assistant


def test_line_of_sight_scores_count_the_half_visible_answer_and_the_fraction_error():
    truth = np.array([0.2, 0.6, 0.9, 0.4])
    ours = np.array([0.6, 0.7, 0.8, 0.3])  # the first one wrong side of a half
    agree_pct, mae = los_scores(truth, ours)
    assert agree_pct == pytest.approx(75.0)
    assert mae == pytest.approx((0.4 + 0.1 + 0.1 + 0.1) / 4)
