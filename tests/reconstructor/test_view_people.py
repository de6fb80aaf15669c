"""``egosurg view --people``: the tracks of ``egosurg people`` drawn in the viewer and named from
its page (reconstructor/replay/view_people.py).

The case is test_view.py's hand-made one (two timestamps, 2.0 and 2.5 s); the people file is
written here as ``egosurg people`` writes one: tracks ``track1..3`` with confidences, one of them
starting at the second timestamp. What a reviewer relies on:

- each track is drawn at its eye at the shown time, and not before it starts;
- a click on a track (the page's own messages over the real websocket, through the viewer's
  gate) picks it, and "Name track" writes the roles file: byte for byte the file ``egosurg
  people name`` writes for the same names, which the review commands read;
- a role given to a second track that overlaps its first in time, or a name that is no name,
  is refused and the file left as it was; a role given to a second track that starts after the
  first ended joins them (one role, the time between a gap); the names written come back when
  the viewer is opened again; a roles file holding a role that is no track (the sim's truth) is
  refused in one line before the page is served;
- with Debian's chromium, the real page lists the tracks and the suggestions (labelled as
  such), and its "Name track" button writes the file.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from protocol.formats.trajectory import Keyframe, Trajectory, read_trajectory_file
from protocol.formats.trajectory import write_trajectories as write_file
from tests.browser import CHROMIUM_MISSING, SKIP_REASON, HeadlessChromium
from tests.helpers import run_egosurg

pytest.importorskip("viser", reason="egosurg view needs viser: pip install -e '.[dev]'")

from reconstructor.replay.names import NamingError
from reconstructor.replay.view import CaseViewer, ViewConfig
from tests.reconstructor.test_view import (
    TIMES_S,
    RawBrowser,
    gui_uuid,
    make_case,
    one_line_error,
)

EYES_M = {  # track -> its eye at each timestamp (None: not yet seen)
    "track1": ((1.0, -1.0, 1.6), (1.0, -1.0, 1.6)),  # stands
    "track2": ((-1.0, 1.0, 1.5), (0.0, 1.0, 1.5)),  # walks along +x
    "track3": (None, (2.0, 1.0, 1.7)),  # comes in at the second timestamp
}


def people_file(path: Path) -> Path:
    tracks = []
    for name, eyes in EYES_M.items():
        keys = tuple(
            Keyframe(time_s=t, eye_m=eye, look_at_m=(0.0, 0.0, 1.0), confidence=0.8)
            for t, eye in zip(TIMES_S, eyes, strict=True)
            if eye is not None
        )
        tracks.append(Trajectory(name=name, keyframes=keys))
    return write_file(path, tracks)


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    return make_case(tmp_path_factory.mktemp("view_people") / "case")


def wait_for(condition, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return bool(condition())


def click_message(node: str) -> dict:
    """What viser's page sends when a scene node is clicked."""
    return {"type": "SceneNodeClickMessage", "name": node, "instance_index": None,
            "ray_origin": (0.0, -3.0, 1.5), "ray_direction": (0.0, 1.0, 0.0),
            "screen_pos": (0.5, 0.5), "modifier": None}  # fmt: skip


CAMERA = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, -3.0, 1.0),
          "fov": 0.9, "near": 0.01, "far": 100.0, "image_height": 400, "image_width": 640,
          "look_at": (0.0, 0.0, 1.0), "up_direction": (0.0, 0.0, 1.0)}  # fmt: skip


def set_value(browser: RawBrowser, viewer, label: str, value) -> None:
    browser.send({"type": "GuiUpdateMessage", "uuid": gui_uuid(viewer, label),
                  "updates": {"value": value}})  # fmt: skip


def test_tracks_are_drawn_at_the_shown_time_and_named_from_the_page(case, tmp_path, caplog):
    people = people_file(tmp_path / "people.toml")
    roles = tmp_path / "roles.toml"
    config = ViewConfig(port=0, people=people, roles=roles, save_to=tmp_path / "v.toml")
    with CaseViewer(case, config) as v:
        for k, t in enumerate(TIMES_S):
            v.slider.value = t
            for name, eyes in EYES_M.items():
                ball = v.naming.markers[name]
                assert ball.visible == (eyes[k] is not None), (name, t)
                if eyes[k] is not None:
                    np.testing.assert_allclose(ball.position, eyes[k], atol=1e-6)
        assert v.naming.track_menu.value == "track1" and not roles.exists()
        # the reviewer clicks track 2's ball, picks "surgeon" and presses "Name track"
        page = RawBrowser(v)
        page.received_bytes(1.0)
        page.send(CAMERA)  # a page sends its camera first: viser counts it in then
        page.send(click_message("/people/track2"))
        assert wait_for(lambda: v.naming.track_menu.value == "track2")
        set_value(page, v, "Name as", "surgeon")
        assert wait_for(lambda: v.naming.role_menu.value == "surgeon")
        set_value(page, v, "Name track", True)
        assert wait_for(roles.exists), caplog.text
        # then types a role of their own for track 1
        page.send(click_message("/people/track1"))
        assert wait_for(lambda: v.naming.track_menu.value == "track1")
        set_value(page, v, "Other name", "anaesthetist")
        assert wait_for(lambda: v.naming.other_role.value == "anaesthetist")
        set_value(page, v, "Name track", True)
        assert wait_for(lambda: len(read_trajectory_file(roles).trajectories) == 2)
        named = roles.read_bytes()
        # "surgeon" once more, for track 3, which is seen at 2.5 s as track 2 is: refused
        set_value(page, v, "Other name", "")
        page.send(click_message("/people/track3"))
        assert wait_for(lambda: v.naming.track_menu.value == "track3")
        set_value(page, v, "Name track", True)
        assert wait_for(lambda: "names not written" in caplog.text), caplog.text
        page.close()
        said = "track2 (2.0-2.5 s) and track3 (at 2.5 s) are both named 'surgeon' but overlap"
        assert f"{said} at 2.5 s" in caplog.text
        assert roles.read_bytes() == named
        # the named roles are the viewer's role cameras now, at the named track's eye
        assert tuple(v.role_menu.options) == ("surgeon", "anaesthetist")
        np.testing.assert_allclose(v.frustums["surgeon"].position, EYES_M["track2"][1], atol=1e-9)
        assert "**surgeon**: track2" in v.naming.list_text.content
        # and the balls say so: labelled with the role, coloured as named
        assert v.naming.labels["track2"].text == "track2 = surgeon"
        assert v.naming.labels["track3"].text == "track3"
        assert tuple(v.naming.markers["track2"].color) != tuple(v.naming.markers["track3"].color)
    # byte for byte what the command writes for the same names
    cli = tmp_path / "cli_roles.toml"
    done = run_egosurg("people", "name", str(people), "track2=surgeon", "track1=anaesthetist",
                       "--out", str(cli))  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert named == cli.read_bytes()
    # opened again, the viewer knows the names it wrote
    with CaseViewer(case, config) as again:
        assert again.naming.names == {"track2": "surgeon", "track1": "anaesthetist"}
        assert set(again.roles) == {"surgeon", "anaesthetist"}
        assert again.naming.label("track2") == "track2 = surgeon"
        again.naming.clear("track1")
        assert [t.name for t in read_trajectory_file(roles).trajectories] == ["surgeon"]
        assert "anaesthetist" not in again.frustums
        with pytest.raises(NamingError, match="write TRACK=ROLE"):
            again.naming.name("track3", "dr who")
        assert [t.name for t in read_trajectory_file(roles).trajectories] == ["surgeon"]


def test_a_second_track_named_with_a_role_already_given_joins_that_role(case, tmp_path, caplog):
    """The surgeon is track1 at 2.0 s, lost, and track2 at 2.5 s: named surgeon both from the
    page, they are one role, the time between them a gap; opened again, both carry the name."""
    eyes = {"track1": (2.0, (1.0, -1.0, 1.6)), "track2": (2.5, (1.2, -0.8, 1.6)),
            "track3": (2.0, (-1.0, 1.0, 1.5))}  # fmt: skip
    people = write_file(tmp_path / "people.toml", [
        Trajectory(name=n, keyframes=(Keyframe(time_s=t, eye_m=eye, look_at_m=(0.0, 0.0, 1.0),
                                               confidence=0.8),))
        for n, (t, eye) in eyes.items()
    ])  # fmt: skip
    roles = tmp_path / "roles.toml"
    config = ViewConfig(port=0, people=people, roles=roles, save_to=tmp_path / "v.toml")
    with CaseViewer(case, config) as v:
        page = RawBrowser(v)
        page.received_bytes(1.0)
        page.send(CAMERA)
        set_value(page, v, "Name as", "surgeon")
        assert wait_for(lambda: v.naming.role_menu.value == "surgeon")
        for track in ("track1", "track2"):
            page.send(click_message(f"/people/{track}"))
            assert wait_for(lambda track=track: v.naming.track_menu.value == track)
            set_value(page, v, "Name track", True)
            assert wait_for(lambda track=track: track in v.naming.names), caplog.text
        page.close()
        (surgeon,) = read_trajectory_file(roles).trajectories
        assert [k.time_s for k in surgeon.keyframes] == [2.0, 2.5]
        assert surgeon.gaps_s == ((2.0, 2.5),)  # nobody followed the surgeon in between
        assert v.naming.labels["track1"].text == "track1 = surgeon"
        assert v.naming.labels["track2"].text == "track2 = surgeon"
        assert "surgeon = track1 + track2: 2.0-2.5 s" in v.naming.list_text.content
        # the role camera stands at each track's eye at its own time
        for t, track in ((2.0, "track1"), (2.5, "track2")):
            v.slider.value = t
            np.testing.assert_allclose(v.frustums["surgeon"].position, eyes[track][1], atol=1e-9)
        # a third track seen at 2.0 s as track1 is: one person cannot be both, refused
        with pytest.raises(NamingError, match=r"track1 .* and track3 .* overlap at 2\.0 s"):
            v.naming.name("track3", "surgeon")
        assert len(read_trajectory_file(roles).trajectories) == 1
    with CaseViewer(case, config) as again:
        assert again.naming.names == {"track1": "surgeon", "track2": "surgeon"}


def test_a_roles_file_that_is_not_of_these_tracks_is_refused_in_one_line(case, tmp_path):
    people = people_file(tmp_path / "people.toml")
    truth = tmp_path / "truth_roles.toml"  # as the sim writes its true eyes: no track's
    eye = Keyframe(time_s=TIMES_S[0], eye_m=(0.3, -0.6, 1.7), look_at_m=(0.0, 0.0, 1.0))
    write_file(truth, [Trajectory(name="surgeon", keyframes=(eye,))])
    with pytest.raises(NamingError, match="no track of the people file"):
        CaseViewer(case, ViewConfig(port=0, people=people, roles=truth))
    line = one_line_error(run_egosurg("view", str(case), "--people", str(people), "--roles",
                                      str(truth), "--port", "0"))  # fmt: skip
    assert "holds 'surgeon', which is no track of the people file" in line
    line = one_line_error(run_egosurg("view", str(case), "--people", str(tmp_path / "gone.toml"),
                                      "--port", "0"))  # fmt: skip
    assert "gone.toml does not exist" in line


@pytest.mark.skipif(CHROMIUM_MISSING, reason=SKIP_REASON)
def test_the_page_lists_the_tracks_and_its_button_names_one(case, tmp_path):
    people = people_file(tmp_path / "people.toml")
    roles = tmp_path / "roles.toml"
    config = ViewConfig(port=0, people=people, roles=roles, save_to=tmp_path / "v.toml")
    browser = HeadlessChromium(tmp_path / "profile", size_px=(1280, 900))
    try:
        with CaseViewer(case, config) as v:
            browser.call("Page.navigate", url=v.url)
            text = lambda: browser.evaluate("document.body.innerText") or ""  # noqa: E731
            assert wait_for(lambda: "suggestion, not an identity" in text(), 45), text()
            for name in EYES_M:
                assert f"{name}:" in text()
            v.naming.pick("track3")  # what a click on its ball does
            v.naming.role_menu.value = "circulator"
            assert wait_for(lambda: v.naming.track_menu.value == "track3")
            click = ("[...document.querySelectorAll('button')]"
                     ".find(b => b.innerText.trim() === 'Name track').click()")  # fmt: skip
            browser.evaluate(click)
            assert wait_for(roles.exists, 20), text()
    finally:
        browser.close()
    (named,) = read_trajectory_file(roles).trajectories
    assert named.name == "circulator"
    assert named.keyframes == read_trajectory_file(people).trajectories[2].keyframes
