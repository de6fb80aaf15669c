"""``egosurg people`` on bodies whose truth is exact (tests/reconstructor/people_bodies.py): the
height map against its slow twin, heads found and tracked, facing from motion and from the arms,
the people file and the naming of tracks, and bad input refused in one line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from protocol.formats.session_id import SessionId
from protocol.formats.trajectory import read_trajectory_file
from reconstructor.people.config import PeopleConfig
from reconstructor.people.heightmap import Grid, top_heights
from reconstructor.people.output import write_people
from reconstructor.people.reference import top_heights_reference
from reconstructor.people.run import find_people
from reconstructor.people.sources import PeopleInputError, Source
from tests.reconstructor.people_bodies import body, room, scene

TIMES_S = tuple(0.5 * k for k in range(14))
SESSION = SessionId(name="bodies", started_unix_ns=1_767_225_600_000_000_000)


def test_the_height_map_matches_its_slow_twin():
    rng = np.random.default_rng(1)
    points = np.concatenate([rng.uniform([-1, -1, 0], [1, 1, 2.2], (4000, 3)),
                             rng.normal([0.2, 0.1, 1.6], 0.05, (800, 3)),
                             [[np.nan, 0, 1], [5.0, 5.0, 1.0]]])  # fmt: skip
    grid = Grid.covering(np.array([-1.0, -1.0]), np.array([1.0, 1.0]), 0.08)
    for min_points in (1, 4, 12):
        kw = {"z_min_m": 0.05, "z_max_m": 2.0, "min_points": min_points}
        fast, slow = top_heights(points, grid, **kw), top_heights_reference(points, grid, **kw)
        assert np.array_equal(np.isnan(fast), np.isnan(slow))
        assert np.nanmax(np.abs(fast - slow)) == 0.0
        assert np.isfinite(fast).sum() > 10


def _source(clouds: list[np.ndarray], name: str) -> Source:
    return Source(path=Path(name), kind="case", times_s=TIMES_S[: len(clouds)], session=SESSION,
                  room_xy_m=(-3.0, -3.0, 3.0, 3.0), _load=lambda k: clouds[k])  # fmt: skip


@pytest.fixture(scope="module")
def bodies():
    """The two bodies, the room learned from a recording of it empty (the worker never moves:
    learned from the case alone, they would be part of the room, see the next test)."""
    rng = np.random.default_rng(0)
    frames = [scene(t, rng) for t in TIMES_S]
    source = _source([f[0] for f in frames], "bodies")
    empty = _source([room(rng) for _ in range(3)], "empty")
    config = PeopleConfig()
    return find_people(source, config, background=empty), [f[1] for f in frames], config


def test_learned_from_the_case_alone_the_walker_is_found_and_a_statue_is_room(bodies):
    rng = np.random.default_rng(5)
    frames = [scene(t, rng) for t in TIMES_S]
    people = find_people(_source([f[0] for f in frames], "bodies"), PeopleConfig())
    assert len(people.tracks) == 1
    assert abs(people.tracks[0].xy()[0][1] - 1.5) < 0.1  # the walker's line, y = 1.5


def test_too_short_a_case_without_the_empty_room_is_refused_in_one_line():
    rng = np.random.default_rng(6)
    source = _source([scene(t, rng)[0] for t in TIMES_S[:4]], "short")
    with pytest.raises(PeopleInputError, match=r"--background EMPTY\.h5"):
        find_people(source, PeopleConfig())


def test_each_body_is_one_track_with_its_head_where_it_is(bodies):
    people, truths, config = bodies
    assert len(people.tracks) == 2, [(t.id, t.xy()[0]) for t in people.tracks]
    for track in people.tracks:
        assert len(track.times_s) >= len(TIMES_S) - 1  # seen (nearly) throughout
    errors = []
    for track in people.tracks:
        for t, pose in zip(track.times_s, people.poses[track.id], strict=True):
            truth = truths[TIMES_S.index(t)]
            centre = pose.eye_m - config.eye_forward_m * pose.gaze()  # back to the head
            errors.append(min(np.linalg.norm(centre[:2] - c[:2]) for c, _ in truth.values()))
    # the head's centre from the top of the column: a few cm (the points are 4 mm noisy)
    assert np.median(errors) <= 0.04, np.median(errors)


def test_a_walker_faces_where_they_go_and_a_worker_faces_their_hands(bodies):
    people, truths, _ = bodies
    for track in people.tracks:
        first = np.asarray(track.detections[0].head_xy_m)
        name = "walker" if first[1] > 1.0 else "worker"
        want = truths[0][name][1]
        yaws = [p.yaw_rad for p in people.poses[track.id]][2:-2]  # motion needs neighbours
        err = [abs((y - want + math.pi) % (2 * math.pi) - math.pi) for y in yaws]
        assert np.median(np.degrees(err)) <= 15, (name, np.degrees(yaws))
        if name == "worker":
            # looks down at the table in front: the table's middle is 0.75 m away, 0.6 m down
            pitch = np.degrees(np.median([p.pitch_rad for p in people.poses[track.id]]))
            assert 25 <= pitch <= 60, pitch


def test_the_people_file_is_a_trajectory_file_with_confidence_gaps_and_session(bodies, tmp_path):
    people, _, config = bodies
    path = write_people(tmp_path / "people.toml", people, config, SESSION)
    file = read_trajectory_file(path)
    assert file.session == SESSION
    assert [t.name for t in file.trajectories] == ["track1", "track2"]
    for t in file.trajectories:
        assert all(0 <= k.confidence <= 1 for k in t.keyframes)  # type: ignore[operator]
        assert all(a < b for a, b in t.gaps_s)


def _egosurg(capsys, *args: str) -> tuple[int, str, str]:
    from protocol.cli import main

    capsys.readouterr()
    code = main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_tracks_named_as_roles_make_the_roles_file_the_review_tools_read(bodies, tmp_path, capsys):
    from reconstructor.replay.cli import pick_trajectory

    people, _, config = bodies
    path = write_people(tmp_path / "people.toml", people, config, SESSION)
    roles = tmp_path / "roles.toml"
    code, out, _ = _egosurg(capsys, "people", "name", str(path), "track2=surgeon",
                            "track1=circulator", "--out", str(roles))  # fmt: skip
    assert code == 0, out
    file = read_trajectory_file(roles)
    assert file.session == SESSION
    assert sorted(t.name for t in file.trajectories) == ["circulator", "surgeon"]
    surgeon = pick_trajectory(None, "surgeon", str(roles))
    track2 = read_trajectory_file(path).trajectories[1]
    assert surgeon.keyframes == track2.keyframes  # the track itself, renamed
    code, out, _ = _egosurg(capsys, "people", "name", str(path), "--list", "--suggest")
    assert code == 0
    assert out.count("suggestion, not an identity") == 2 and "track1:" in out


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (("track9=surgeon",), "no track9 in the people file; it has track1, track2"),
        (("track1=surgeon", "track2=surgeon"), "are both named 'surgeon' but overlap"),
        (("surgeon",), "write TRACK=ROLE"),
    ],
)
def test_bad_names_are_refused_in_one_line(bodies, tmp_path, capsys, args, says):
    people, _, config = bodies
    path = write_people(tmp_path / "people.toml", people, config, SESSION)
    code, _, err = _egosurg(capsys, "people", "name", str(path), *args, "--out",
                            str(tmp_path / "roles.toml"))  # fmt: skip
    assert code == 2
    assert says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "roles.toml").exists()


def test_what_is_not_a_case_or_a_session_is_refused_in_one_line(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello")
    cases = (
        (tmp_path, "is neither a case folder"),
        (tmp_path / "notes.txt", "is neither a case folder"),
        (tmp_path / "gone", "does not exist"),
    )
    for given, says in cases:
        code, _, err = _egosurg(capsys, "people", str(given), "--out", str(tmp_path / "p.toml"))
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err


def test_a_confidence_or_gap_out_of_range_is_refused_with_the_entry_named(tmp_path):
    from protocol.formats.trajectory import TrajectoryFileError

    base = ('format = "egosurg-trajectories"\nformat_version = 1\n[[trajectories]]\n'
            'name = "track1"\n{gaps}[[trajectories.keyframes]]\ntime_s = 1.0\n'
            "eye_m = [0, 0, 1.7]\nlook_at_m = [1, 0, 1.5]\nconfidence = {conf}\n")  # fmt: skip
    for gaps, conf, says in (("", "1.5", "confidence 1.5"),
                             ("gaps_s = [[3.0, 2.0]]\n", "0.5", "from < to")):  # fmt: skip
        path = tmp_path / "p.toml"
        path.write_text(base.format(gaps=gaps, conf=conf))
        with pytest.raises(TrajectoryFileError, match=says):
            read_trajectory_file(path)


def test_a_cases_camera_masks_keep_what_a_second_camera_saw_as_the_clouds_do():
    """The people stage's check against stereo streaks (a wrong match lies along one camera's
    rays, where no other camera sees anything), on a case's stored cells with their camera
    masks, keeps exactly what it keeps on the cameras' own clouds: a surface three cameras saw
    stays, a streak only one saw goes, and a point beside a second camera's (the next cube) is
    confirmed by it."""
    from reconstructor.people.sources import SEEN_TWICE_CELL_M, seen_twice, seen_twice_cells

    rng = np.random.default_rng(5)
    cell = 0.02
    room_xy = (-2.0, -2.0, 2.0, 2.0)
    surface = np.stack(np.meshgrid(np.arange(-0.5, 0.5, cell), np.arange(-0.5, 0.5, cell),
                                   [1.0], indexing="ij"), -1).reshape(-1, 3) + cell / 2  # fmt: skip
    streak = np.array([1.2, 0.3, 0.5]) + np.arange(40)[:, None] * np.array([0.0, 0.0, cell])
    clouds = [
        np.concatenate([surface, streak + cell / 2]),  # camera 0: the surface and a streak
        surface[rng.random(len(surface)) < 0.5],  # camera 1: half the surface
        surface[rng.random(len(surface)) < 0.5] + [0.0, 0.0, cell],  # camera 2: a cube above
        np.array([[-1.5, -1.5, 0.3]]),  # camera 3: a lone point nobody else saw
    ]
    cells: dict[tuple[int, int, int], int] = {}
    for bit, cloud in enumerate(clouds):
        for c in map(tuple, np.floor(cloud / cell).astype(int)):
            cells[c] = cells.get(c, 0) | (1 << bit)
    keys = np.array(list(cells))
    points = (keys + 0.5) * cell
    masks = np.array(list(cells.values()), np.uint8)
    kept = seen_twice_cells(points, masks, 4, room_xy, SEEN_TWICE_CELL_M)
    from_clouds = seen_twice(clouds, room_xy, SEEN_TWICE_CELL_M)
    expected = np.unique(np.round(from_clouds / cell, 3), axis=0)
    assert np.array_equal(np.unique(np.round(kept / cell, 3), axis=0), expected)
    assert len(kept) >= len(surface)  # the surface stays, every cell of it
    assert not np.any(np.isclose(kept[:, 0], 1.2 + cell / 2))  # none of the streak
    assert not np.any(np.all(np.isclose(kept, [-1.5 + cell / 2, -1.5 + cell / 2, 0.31]), 1))


def _legs_hidden(points: np.ndarray, xy: tuple[float, float], below_m: float) -> np.ndarray:
    """``points`` without those of the body at ``xy`` (within 0.35 m) lower than ``below_m``:
    legs behind the table's drapes or a neighbour, as the rig sees them."""
    near = np.hypot(points[:, 0] - xy[0], points[:, 1] - xy[1]) < 0.35
    return points[~(near & (points[:, 2] > 0.02) & (points[:, 2] < below_m))]


def test_a_person_whose_legs_are_hidden_for_a_while_is_followed_and_a_legless_column_is_no_one():
    """A worker at the table whose legs are hidden below 0.8 m for a second (two timestamps:
    about half the slices from the knees to the neck show no body there) is followed through
    it, the track taking their head there rather than leaving a gap; a body whose legs are
    hidden all along (a head and shoulders on a stand) starts no track."""
    rng = np.random.default_rng(8)
    worker_xy, stand_xy = (0.3, 0.75), (-1.5, -1.5)
    hidden = {6, 7}
    clouds = []
    for k, t in enumerate(TIMES_S):
        points, _ = scene(t, rng)
        stand = body(rng, stand_xy, 0.0, 1.75)
        points = np.concatenate([points, _legs_hidden(stand, stand_xy, 0.8)])
        clouds.append(_legs_hidden(points, worker_xy, 0.8) if k in hidden else points)
    empty = _source([room(rng) for _ in range(3)], "empty")
    people = find_people(_source(clouds, "hidden legs"), PeopleConfig(), background=empty)
    workers = [tr for tr in people.tracks if np.hypot(*(tr.xy()[0] - worker_xy)) < 0.2]
    assert len(workers) == 1, [tr.xy()[0] for tr in people.tracks]
    seen = {round(t / 0.5) for t in workers[0].times_s}
    assert hidden <= seen, sorted(seen)  # its head taken where the legs were hidden
    assert not [tr for tr in people.tracks if np.hypot(*(tr.xy()[0] - stand_xy)) < 0.5]
