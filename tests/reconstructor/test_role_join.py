"""One role from several tracks (reconstructor/replay/names.py): a person lost behind the table
comes back as a new track, and the reviewer names both ``surgeon``. What a reviewer relies on:

- ``egosurg people name people.toml track1=surgeon track3=surgeon`` writes ONE surgeon: the
  tracks' keyframes in time order, each track's own gap kept and the hand-over between them a
  gap; the command and ``--list`` say which tracks the role joins, and the file read back gives
  both tracks their name (what the viewer does when it opens the roles file);
- two tracks of one role that share an instant are refused in one line naming both and the
  seconds, and no file is written;
- replay shows no view from inside a gap (a grey NOT FOLLOWED card, counted), sightline
  gives no answer there (no row; a warning with the count), nor draws another role that is in
  one of its gaps, and the case report renders no role view there.

The case is written by hand, as test_view.py's: a wall of Gaussians at four timestamps.
"""

from __future__ import annotations

import csv
from pathlib import Path

import av
import numpy as np
import pytest

from protocol.formats.site import SiteBox, site_toml
from protocol.formats.trajectory import Keyframe, Trajectory, read_trajectory_file
from protocol.formats.trajectory import write_trajectories as write_file
from reconstructor.replay.names import NamingError, name_tracks, names_in
from reconstructor.replay.path import CameraPath
from tests.helpers import egosurg_in_process as egosurg

pytest.importorskip("viser", reason="test_view.py's wall needs viser's test module to import")
from tests.reconstructor.test_view import make_case

CASE_TIMES_S = (2.0, 2.5, 2.75, 3.0)
LOOK_AT_M = (0.0, 0.0, 1.0)  # the wall's middle: every eye looks at it


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    return make_case(tmp_path_factory.mktemp("role_join") / "case", CASE_TIMES_S)


def _track(name: str, times: tuple[float, ...], eye, gaps=()) -> Trajectory:
    keys = tuple(Keyframe(time_s=t, eye_m=eye, look_at_m=LOOK_AT_M, confidence=0.8) for t in times)
    return Trajectory(name=name, keyframes=keys, gaps_s=gaps)


# the surgeon: track1 (hidden at 2.0 s: its own gap 1.5-2.5 s), lost, back as track3 at 3.0 s;
# track2 is someone else all along; track4 a second head beside the surgeon at 2.5-3.5 s
TRACKS = (
    _track("track1", (1.0, 1.5, 2.5), (0.3, -3.0, 1.1), gaps=((1.5, 2.5),)),
    _track("track2", (1.0, 2.0, 3.0, 4.0), (-1.0, -2.5, 1.5)),
    _track("track3", (3.0, 3.5, 4.0), (0.5, -3.0, 1.1)),
    _track("track4", (2.5, 3.5), (0.4, -2.9, 1.1)),
)


def test_two_tracks_named_one_role_make_one_trajectory_with_the_hand_over_a_gap(tmp_path, capsys):
    people = write_file(tmp_path / "people.toml", TRACKS)
    roles = tmp_path / "roles.toml"
    ran = egosurg(capsys, "people", "name", str(people), "track3=surgeon", "track1=surgeon",
                  "track2=assistant", "--out", str(roles))  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    assert "surgeon = track1 + track3: 1.0-4.0 s, not followed 2.5-3.0 s" in ran.stdout
    surgeon, assistant = read_trajectory_file(roles).trajectories
    assert (surgeon.name, assistant.name) == ("surgeon", "assistant")
    assert [k.time_s for k in surgeon.keyframes] == [1.0, 1.5, 2.5, 3.0, 3.5, 4.0]
    assert [k.eye_m for k in surgeon.keyframes] == [(0.3, -3.0, 1.1)] * 3 + [(0.5, -3.0, 1.1)] * 3
    assert surgeon.gaps_s == ((1.5, 2.5), (2.5, 3.0))  # its own, then the hand-over
    # read back (as the viewer does on opening it): each track has its name again
    tracks = read_trajectory_file(people).trajectories
    given = names_in(read_trajectory_file(roles).trajectories, tracks, str(roles))
    assert given == {"track1": "surgeon", "track3": "surgeon", "track2": "assistant"}
    ran = egosurg(capsys, "people", "name", str(people), "--list", "--out", str(roles))
    assert ran.returncode == 0, ran.stderr
    assert "surgeon = track1 + track3" in ran.stdout and "assistant = track2: " in ran.stdout
    # a role that joins tracks of this file the wrong way round (no hand-over gap) is no join
    forged = tmp_path / "forged.toml"
    write_file(forged, [Trajectory(name="surgeon", keyframes=surgeon.keyframes,
                                   gaps_s=((1.5, 2.5),))])  # fmt: skip
    with pytest.raises(NamingError, match="no track of the people file"):
        names_in(read_trajectory_file(forged).trajectories, tracks, str(forged))


@pytest.mark.parametrize(
    ("names", "says"),
    [
        (("track1=surgeon", "track4=surgeon"),
         "track1 (1.0-2.5 s) and track4 (2.5-3.5 s) are both named 'surgeon' but overlap at 2.5 s"),
        (("track3=surgeon", "track4=surgeon"),
         "track4 (2.5-3.5 s) and track3 (3.0-4.0 s) are both named 'surgeon' but overlap "
         "3.0-3.5 s"),
    ],
)  # fmt: skip
def test_tracks_of_one_role_that_overlap_are_refused_in_one_line(tmp_path, capsys, names, says):
    people = write_file(tmp_path / "people.toml", TRACKS)
    roles = tmp_path / "roles.toml"
    ran = egosurg(capsys, "people", "name", str(people), *names, "--out", str(roles))
    assert ran.returncode == 2
    assert says in ran.stderr and len(ran.stderr.strip().splitlines()) == 1, ran.stderr
    assert not roles.exists()


def _frames(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def test_replay_and_sightline_show_nothing_from_inside_a_joined_roles_gaps(
    case, tmp_path, capsys, caplog
):
    people = write_file(tmp_path / "people.toml", TRACKS)
    roles = tmp_path / "roles.toml"
    ran = egosurg(capsys, "people", "name", str(people), "track1=surgeon", "track3=surgeon",
                  "track2=assistant", "--out", str(roles))  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    # replay 2.0-3.0 s at 4 frames/s: 2.0 and 2.25 s fall in track1's own gap, 2.75 s in the
    # hand-over; 2.5 and 3.0 s are keyframes: seen
    out = tmp_path / "surgeon.mp4"
    ran = egosurg(capsys, "replay", str(case), "--role", "surgeon", "--roles", str(roles),
                  "--from", "2.0", "--to", "3.0", "--fps", "4", "--size", "320x200",
                  "--out", str(out))  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    assert "3 of 5 frames fall in the path's gaps" in ran.stderr
    frames = _frames(out)
    assert len(frames) == 5
    below_text = (slice(120, 200), slice(0, 320))  # under the burned-in lines
    for k, frame in enumerate(frames):
        part = frame[below_text].astype(int)
        flat = np.abs(part - 64).max() <= 6  # the card's grey, through H.264
        assert flat == (k in (0, 1, 3)), (k, part.min(), part.max())
    # sightline answers at 2.5 and 3.0 s only: 2.0 and 2.75 s fall in the viewer's gaps
    site = tmp_path / "site.toml"
    site.write_text(site_toml([SiteBox(name="screen", centre_m=(0.0, -1.5, 1.2),
                                       size_m=(0.5, 0.05, 0.3))]))  # fmt: skip
    los = tmp_path / "los"
    ran = egosurg(capsys, "sightline", str(case), "--viewer", "surgeon", "--roles", str(roles),
                  "--target", "screen", "--site", str(site), "--out", str(los))  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    rows = list(csv.DictReader((los / "sightline.csv").open()))
    assert [float(r["t_s"]) for r in rows] == [2.5, 3.0]
    assert "2 of 4 timestamps fall in surgeon's gaps (1.5-2.5 s, 2.5-3.0 s" in caplog.text
    assert sorted(p.name for p in los.glob("plan_*.png")) == [
        "plan_00002.500.png", "plan_00003.000.png",
    ]  # fmt: skip
    # another role inside one of its gaps stands nowhere on the plans and blocks no line
    from reconstructor.replay.sightline_pictures import SightScene

    (surgeon,) = name_tracks(TRACKS, {"track1": "surgeon", "track3": "surgeon"})
    scene = SightScene(None, (), (CameraPath(surgeon),), clock=None)  # type: ignore[arg-type]
    assert scene.people_at(2.75, "assistant") == {}
    assert set(scene.people_at(3.0, "assistant")) == {"surgeon"}
    # nor does the case report render the role's view there (it lists the time as uncovered)
    from reconstructor.report.views import _inside

    assert [_inside(CameraPath(surgeon), t) for t in CASE_TIMES_S] == [False, True, False, True]
