"""The demo's naming of tracks by the sim's truth (sim/demo_names.py): each track after the
person whose true eye is nearest it, each track once, only within 0.5 m; a person takes several
tracks where theirs broke, never two at once."""

from __future__ import annotations

import numpy as np

from protocol.formats.trajectory import Keyframe, Trajectory, write_trajectories
from sim.demo_names import covering, name_by_truth


def _path(name: str, eyes: list[tuple[float, float, float]], t0: float = 0.0) -> Trajectory:
    keys = tuple(
        Keyframe(time_s=t0 + k, eye_m=eye, look_at_m=(0.0, 0.0, 1.0)) for k, eye in enumerate(eyes)
    )
    return Trajectory(name=name, keyframes=keys)


def true_eyes(t_s: float) -> dict[str, np.ndarray]:
    """Three people: two standing, the circulator walking along -x at 0.5 m/s."""
    return {
        "surgeon": np.array([0.3, -0.6, 1.6]),
        "anaesthetist": np.array([-1.8, 0.0, 1.5]),
        "circulator": np.array([2.0 - 0.5 * t_s, 2.0, 1.6]),
    }


def test_each_track_is_named_after_the_nearest_true_person_once_and_only_near(tmp_path):
    people = write_trajectories(tmp_path / "people.toml", [
        _path("track1", [(-1.7, 0.1, 1.5)] * 6),  # the anaesthetist, 14 cm off
        _path("track2", [(0.35, -0.55, 1.6)] * 3, t0=2.0),  # the surgeon, from 2 s
        _path("track3", [(0.2, -0.5, 1.6)] * 6),  # the surgeon too, but farther: not named
        _path("track4", [(2.0, 2.0, 1.6)] * 6),  # where the circulator was at 0 s only
        _path("track5", [(2.0 - 0.5 * k, 2.1, 1.6) for k in range(6)]),  # the circulator
    ])  # fmt: skip
    named = {n.track: n.role for n in name_by_truth(people, true_eyes)}
    assert named == {"track1": "anaesthetist", "track2": "surgeon", "track5": "circulator"}
    # a case at 1, 2, 3, 4, 5 and 6 s: track2 (2-4 s) spans three of its timestamps, the others
    # (0-5 s) five; ties go to the longer track, then the name
    named_roles = name_by_truth(people, true_eyes)
    assert covering(named_roles, people, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) == [
        "circulator", "anaesthetist", "surgeon",
    ]  # fmt: skip
    assert covering(named_roles, people, [4.5, 5.0, 5.5]) == ["circulator", "anaesthetist"]
    assert covering(named_roles, people, [5.0, 6.0]) == []


def test_a_person_whose_track_broke_takes_each_of_its_pieces_that_do_not_overlap(tmp_path):
    """The surgeon is lost behind the table at 2 s and comes back as a new track at 3.5 s: both
    are named surgeon (the roles file joins them); a second head beside the surgeon over
    1-4 s overlaps both pieces and is not named, though within reach; the anaesthetist's one
    track is named as before."""
    people = write_trajectories(tmp_path / "people.toml", [
        _path("track1", [(0.25, -0.6, 1.6)] * 3),  # the surgeon, 0-2 s
        _path("track2", [(-1.7, 0.0, 1.5)] * 7),  # the anaesthetist
        _path("track3", [(0.4, -0.45, 1.6)] * 4, t0=1.0),  # beside the surgeon, 1-4 s
        _path("track4", [(0.3, -0.65, 1.6)] * 3, t0=3.5),  # the surgeon again, 3.5-5.5 s
    ])  # fmt: skip
    named = {n.track: n.role for n in name_by_truth(people, true_eyes)}
    assert named == {"track1": "surgeon", "track2": "anaesthetist", "track4": "surgeon"}
    named_roles = name_by_truth(people, true_eyes)
    # a case at 0, 2, 3 and 5 s: the surgeon is known at 0, 2 and 5 s (3 s falls between the
    # two pieces), the anaesthetist at all four
    assert covering(named_roles, people, [0.0, 2.0, 3.0, 5.0], min_timestamps=3) == [
        "anaesthetist", "surgeon",
    ]  # fmt: skip
    assert covering(named_roles, people, [2.5, 3.0], min_timestamps=1) == ["anaesthetist"]
