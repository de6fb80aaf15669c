"""Where ``egosurg people``'s people look, on detections placed by hand, as a reviewer relies on
it: a team standing round a table looks at its middle even where each one's shoulder line is
found tens of degrees off, down to the work on it; one of them who faces away from the team
(a console behind them) is not turned round; two people working back to back are not
turned to face each other; a person standing still with nothing raised seen in front of them (the
table under their arms hidden from the cameras) looks down at their hands, a walker a little down
ahead of them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reconstructor.errors import ReconstructConfigError
from reconstructor.people.config import PeopleConfig
from reconstructor.people.detect import Detection
from reconstructor.people.run import people_from_detections

TIMES_S = tuple(0.5 * k for k in range(16))
NO_SURFACE = (math.inf, math.inf)


def head(
    x: float,
    y: float,
    axis_rad: float,
    reach_m: tuple[float, float] = (0.0, 0.0),
    surface_m: tuple[float, float] = NO_SURFACE,
    pitch_rad: float = math.radians(9.0),
) -> Detection:
    """A sure head 1.75 m high whose shoulder line runs along ``axis_rad``; the detector's gaze
    pitch for each side is ``pitch_rad``, as it gives with no raised surface seen."""
    return Detection(head_xy_m=(x, y), top_m=1.75, shoulder_axis_rad=axis_rad, reach_m=reach_m,
                     gaze_pitch_rad=(pitch_rad, pitch_rad), surface_m=surface_m,
                     confidence=0.9)  # fmt: skip


def off_deg(a: float, b: float) -> float:
    return abs(math.degrees((a - b + math.pi) % (2 * math.pi) - math.pi))


def where_gaze_lands(pose, z_m: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    """(x, y) where the pose's gaze ray comes down to height ``z_m``."""
    gaze = pose.gaze()
    assert gaze[2] < 0, "looks up or level"
    return pose.eye_m[:2] + gaze[:2] * (pose.eye_m[2] - z_m) / -gaze[2]


def _round_the_table(extra: list[tuple[str, Detection]] | None = None):  # type: ignore[no-untyped-def]
    """Four people 0.8 m from the middle of a table at the origin, each one's shoulder line
    found 25 degrees off square to it, one way at one timestamp and the other way at the next
    (as arms and neighbours bend it); their arms reach towards the table."""
    places = {"north": 90, "east": 0, "south": -90, "west": 180}
    frames = []
    for k, t in enumerate(TIMES_S):
        heads = []
        for j, bearing_deg in enumerate(places.values()):
            b = math.radians(bearing_deg)
            xy = (0.8 * math.cos(b), 0.8 * math.sin(b))
            axis = b + math.pi / 2 + math.radians(25 * (-1) ** (j + k))  # square, then off
            plus_normal = np.array([math.cos(axis + math.pi / 2), math.sin(axis + math.pi / 2)])
            inwards = plus_normal @ -np.array([math.cos(b), math.sin(b)]) > 0
            heads.append(head(*xy, axis, (0.1, 0.0) if inwards else (0.0, 0.1)))
        frames.append((t, heads + [d for _, d in extra or []]))
    tracks, poses = people_from_detections(frames, PeopleConfig())
    where = {n: (0.8 * math.cos(math.radians(b)), 0.8 * math.sin(math.radians(b)))
             for n, b in places.items()} | {n: d.head_xy_m for n, d in extra or []}  # fmt: skip
    named = {}
    for tr in tracks:
        xy = tr.xy()[0]
        named[min(where, key=lambda n: math.hypot(*(xy - np.asarray(where[n]))))] = poses[tr.id]
    assert len(named) == len(where)
    return named


def test_a_team_round_a_table_looks_at_its_middle_though_each_shoulder_line_is_off():
    for name, poses in _round_the_table().items():
        for p in poses:
            towards = math.atan2(-p.eye_m[1], -p.eye_m[0])
            assert off_deg(p.yaw_rad, towards) < 8, (name, off_deg(p.yaw_rad, towards))
            # and down at the work on the table, not over it: the gaze comes down to 1 m
            # (an OR table's working height) within 0.3 m of its middle
            assert np.hypot(*where_gaze_lands(p, 1.0)) < 0.3, name


def test_one_who_faces_away_from_the_team_at_a_console_is_not_turned_round():
    # 1.3 m from the table's middle, back to it: a console 0.5 m in front of them, hands on it
    away = head(-1.3, -0.6, math.pi / 2, reach_m=(0.3, 0.0), surface_m=(0.5, math.inf),
                pitch_rad=0.4)  # fmt: skip
    poses = _round_the_table([("console", away)])["console"]
    facing = away.normal_rad(0)  # +normal, -x: away from the table, at the console
    assert all(off_deg(p.yaw_rad, facing) < 1 for p in poses)
    assert all(p.pitch_rad == pytest.approx(0.4) for p in poses)  # the console's, as found


def test_two_working_back_to_back_are_not_turned_to_face_each_other():
    # two cleaners 1.2 m apart, back to back, each wiping in front of them: arms 10 cm further
    # out on their own front (away from the other), nothing raised seen. A pair has no shared
    # space in front of each: the other's side is not their front
    west = [head(-0.6, 0.0, math.pi / 2, reach_m=(0.1, 0.0))] * len(TIMES_S)  # +normal: -x
    east = [head(0.6, 0.0, math.pi / 2, reach_m=(0.0, 0.1))] * len(TIMES_S)  # -normal: +x
    frames = [(t, [a, b]) for t, a, b in zip(TIMES_S, west, east, strict=True)]
    tracks, poses = people_from_detections(frames, PeopleConfig())
    assert len(tracks) == 2
    for tr in tracks:
        away = 0.0 if tr.xy()[0][0] > 0 else math.pi  # away from the other, where the arms are
        assert all(off_deg(p.yaw_rad, away) < 1 for p in poses[tr.id]), tr.xy()[0]


def test_standing_with_nothing_raised_seen_in_front_they_look_at_their_hands_walkers_ahead():
    # a person standing still, their arms out on +normal, nothing raised seen on either side;
    # another walking past at 1 m/s, 3 m away
    still = [head(0.0, 0.0, 0.0, reach_m=(0.15, 0.0))] * len(TIMES_S)
    walker = [head(-3.0 + 1.0 * t, 3.0, math.pi / 2) for t in TIMES_S]
    frames = [(t, [a, b]) for t, a, b in zip(TIMES_S, still, walker, strict=True)]
    tracks, poses = people_from_detections(frames, PeopleConfig())
    assert len(tracks) == 2
    for tr in tracks:
        inner = poses[tr.id][2:-2]  # motion needs neighbours
        if tr.xy()[0][1] < 1:  # the one standing still
            for p in inner:
                assert off_deg(p.yaw_rad, math.pi / 2) < 1  # towards their arms (+y)
                hands = where_gaze_lands(p, 1.0)  # work height
                assert 0.5 <= np.hypot(*(hands - tr.xy()[0])) <= 0.9, hands
        else:
            for p in inner:
                assert off_deg(p.yaw_rad, 0.0) < 5  # where they go (+x)
                assert 0 < math.degrees(p.pitch_rad) <= 15


@pytest.mark.parametrize("field, value", [("ospace_angle_deg", 0.0), ("ospace_angle_deg", 120.0),
                                          ("ospace_reach_m", -1.0)])  # fmt: skip
def test_a_shared_point_setting_that_cannot_work_is_refused_in_one_line(field, value):
    with pytest.raises(ReconstructConfigError, match=field):
        PeopleConfig(**{field: value})
