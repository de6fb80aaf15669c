"""``egosurg view --people people.toml``: name the tracks of ``egosurg people`` in the browser.

Each track is a ball at its eye at the shown time, labelled with its track id (and its role once
named): green while unnamed, blue once named, grey inside one of its gaps (hidden from every
camera: the ball stands where the replay would put the eye, not where anyone saw it), and not
drawn before the track starts or after it ends. Clicking a ball picks its track under "Track";
"Name track" gives it the role chosen under "Name as" (or typed under "Other name", which wins
when not empty) and writes the roles file (``--roles``; default ``roles.toml`` beside the people
file) through ``reconstructor.replay.names``: the file ``egosurg people name`` writes, in its
format, which replay, sightline, sterile, the report and the viewer's role cameras read. "Clear
name" takes a track's name back. The panel lists each track (when, where it mostly stands, how
sure), each role with the tracks it joins, and the room's suggestions, labelled as suggestions:
they are never written as names.

A person lost and found again is a new track: naming a second track with a role already given
joins it to that role (its keyframes after the first track's, the time between a gap: see
``names.py``); a track that overlaps the role's others in time is refused in one line, the file
left as it was. A roles file that already exists is read as the names it gives these tracks (a
role is the join of the tracks whose keyframes it carries); one holding a role that is no track
of the people file (the sim's truth, a path drawn by hand) is refused in one line before the
page is served, since writing the names would replace it. Only a browser that came through the
viewer's gate (``view_boundary``) writes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import UserError
from protocol.formats.trajectory import Trajectory, TrajectoryFile, read_trajectory_file
from reconstructor.replay.names import describe, names_in, role_lines, suggest, write_roles
from reconstructor.replay.path import CameraPath
from reconstructor.replay.session_check import CaseInputs

log = logging.getLogger(__name__)

UNNAMED_COLOUR = (30, 170, 80)
NAMED_COLOUR = (40, 110, 220)
HIDDEN_COLOUR = (150, 150, 150)
MARKER_RADIUS_M = 0.12  # about a head
# the roles the review tools' examples use; "Other name" takes any other name
COMMON_ROLES = (
    "surgeon", "assistant", "anaesthetist", "nurse_scrub", "circulator", "robot_assistant",
)  # fmt: skip


def default_roles_path(people: Path) -> Path:
    return people.parent / "roles.toml"


class PeopleNaming:
    """The tracks of a people file drawn in a viewer's scene and named from its panel.

    ``on_roles`` is called with the roles (a list of trajectories) each time the roles file is
    written, so that the viewer's role cameras follow."""

    def __init__(
        self,
        people: Path,
        roles: Path,
        inputs: CaseInputs,
        on_roles: Callable[[tuple[Trajectory, ...]], None],
    ) -> None:
        self.people_path, self.roles_path = people, roles
        inputs.trajectories(people)  # a people file of another session: refused in one line
        self.file: TrajectoryFile = read_trajectory_file(people)
        self.tracks = {t.name: t for t in self.file.trajectories}
        self.paths = {t.name: CameraPath(t) for t in self.file.trajectories}
        self.names: dict[str, str] = {}
        if roles.is_file():
            self.names = names_in(inputs.trajectories(roles), self.file.trajectories, str(roles))
        self._on_roles = on_roles
        self.markers: dict[str, Any] = {}  # track -> its ball in the scene
        self.labels: dict[str, Any] = {}  # track -> the label over its ball
        self._server: Any = None
        self._trusts: Callable[[int], bool] = lambda _: False

    # --- page -----------------------------------------------------------------------------
    def build(self, server: Any, trusts: Callable[[int], bool]) -> None:
        """The "People" folder of the panel; ``trusts(client_id)``: the page may write."""
        self._server, self._trusts = server, trusts
        gui = server.gui
        with gui.add_folder("People"):
            self.list_text = gui.add_markdown(self.list_markdown())
            self.track_menu = gui.add_dropdown("Track", tuple(self.tracks))
            self.role_menu = gui.add_dropdown("Name as", COMMON_ROLES)
            self.other_role = gui.add_text("Other name", "", hint="any role: letters, digits, - _")
            name = gui.add_button("Name track", hint=f"writes {self.roles_path}")
            name.on_click(lambda event: self.name_from_page(event.client))
            clear = gui.add_button("Clear name")
            clear.on_click(lambda event: self.clear_from_page(event.client))

    def list_markdown(self) -> str:
        lines = [f"Names go to `{self.roles_path}`.", ""]
        for name, track in self.tracks.items():
            role = self.names.get(name)
            lines.append(f"- {'**' + role + '**: ' if role else ''}{describe(track)}")
        if self.names:
            lines += ["", "Roles and the tracks they join:", ""]
            lines += [f"- {line}" for line in role_lines(self.names, self.file.trajectories)]
        lines += ["", "Suggestions from where each stands (not identities):", ""]
        lines += [f"- {line}" for line in suggest(self.file.trajectories)]
        return "\n".join(lines)

    def label(self, track: str) -> str:
        role = self.names.get(track)
        return f"{track} = {role}" if role else track

    def draw(self, t_s: float) -> None:
        """Each track's ball at case time ``t_s`` (hidden outside its span). The nodes are made
        once and then moved: a long case has many tracks, and the slider moves often."""
        scene = self._server.scene
        for name, path in self.paths.items():
            t0, t1 = path.span_s
            inside = t0 - 1e-6 <= t_s <= t1 + 1e-6
            eye = path.pose(float(np.clip(t_s, t0, t1))).centre_m
            hidden = any(a < t_s < b for a, b in self.tracks[name].gaps_s)
            colour = HIDDEN_COLOUR if hidden else NAMED_COLOUR if name in self.names else (
                UNNAMED_COLOUR
            )  # fmt: skip
            text = self.label(name) + (" (hidden)" if hidden else "")
            if name not in self.markers:
                ball = scene.add_icosphere(
                    f"/people/{name}", radius=MARKER_RADIUS_M, color=colour, position=eye,
                    visible=inside,
                )  # fmt: skip
                ball.on_click(lambda _, name=name: self.pick(name))
                self.markers[name] = ball
                self.labels[name] = scene.add_label(
                    f"/people/{name}/label", text, position=(0.0, 0.0, 0.2)
                )
                continue
            ball, label = self.markers[name], self.labels[name]
            ball.position, ball.visible, ball.color = eye, inside, colour
            label.text = text

    def pick(self, track: str) -> None:
        """What a click on a track's ball does: pick it under "Track"."""
        if track in self.tracks:
            self.track_menu.value = track

    # --- naming ---------------------------------------------------------------------------
    def chosen_role(self) -> str:
        return str(self.other_role.value).strip() or str(self.role_menu.value)

    def name(self, track: str, role: str) -> tuple[Trajectory, ...]:
        """Give ``track`` the name ``role`` and write the roles file (a role already given
        joins this track too); ``UserError`` (one line, the file left as it was) for an unknown
        track, a bad name or a track that overlaps the role's others in time."""
        names = {t: r for t, r in self.names.items() if t != track}
        names[track] = role
        return self._write(names)

    def clear(self, track: str) -> tuple[Trajectory, ...]:
        if track not in self.names:
            raise UserError(f"{track} has no name to clear")
        names = {t: r for t, r in self.names.items() if t != track}
        if not names:
            raise UserError(
                f"{track} is the only named track and a roles file holds at least one role: "
                f"name another first, or delete {self.roles_path}"
            )
        return self._write(names)

    def _write(self, names: dict[str, str]) -> tuple[Trajectory, ...]:
        roles = tuple(write_roles(self.roles_path, self.file, names))
        self.names = names
        self.list_text.content = self.list_markdown()
        self._on_roles(roles)
        return roles

    def name_from_page(self, client: Any) -> None:
        self._from_page(client, lambda: self.name(str(self.track_menu.value), self.chosen_role()))

    def clear_from_page(self, client: Any) -> None:
        self._from_page(client, lambda: self.clear(str(self.track_menu.value)))

    def _from_page(self, client: Any, act: Callable[[], tuple[Trajectory, ...]]) -> None:
        if client is None or not self._trusts(client.client_id):
            log.warning("viewer: names not written: the request came from a page without the token")
            return
        try:
            roles = act()
        except UserError as exc:
            log.warning("viewer: names not written: %s", exc)
            client.add_notification("Not named", str(exc)[:300], color="red")
            return
        said = ", ".join(r.name for r in roles)
        log.info("viewer: wrote %s (%s)", self.roles_path, said)
        client.add_notification("Names saved", f"{self.roles_path}: {said}", auto_close_seconds=4.0)
