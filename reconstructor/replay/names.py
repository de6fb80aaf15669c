"""Tracks named as roles: ``egosurg people name people.toml track3=surgeon ...`` writes the roles
file the review tools read (``--roles``): the named tracks only, renamed, with their confidences,
gaps and session. Suggestions from the room (``suggest``) are printed as suggestions, never
written as names: where a track stands says what it may be, not who it is.

Here, in replay/, not in people/: the viewer names tracks too (``view_people.py``), and people/
comes after replay/ in the reconstructor's parts (tests/test_package_rules.py); both the
``egosurg people name`` command and the viewer write through ``write_roles``.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from protocol.formats.trajectory import Trajectory, TrajectoryFile, write_trajectories
from reconstructor.errors import CaseReplayError


class NamingError(CaseReplayError, ValueError):
    """Names that cannot be given; the message says which and what to write instead."""


_PAIR = re.compile(r"^(track\d+)=([A-Za-z0-9_-]+)$")


def parse_names(pairs: list[str]) -> dict[str, str]:
    """``["track3=surgeon", ...]`` -> ``{"track3": "surgeon"}``; one line naming a bad pair."""
    out: dict[str, str] = {}
    for text in pairs:
        m = _PAIR.match(text.strip())
        if m is None:
            raise NamingError(
                f"{text!r}: write TRACK=ROLE, e.g. track3=surgeon (a role is letters, digits, "
                "'-' or '_')"
            )
        track, role = m.groups()
        if track in out:
            raise NamingError(f"{track} is named twice ({out[track]}, {role}): name it once")
        if role in out.values():
            raise NamingError(f"two tracks are named {role!r}: give each role one track")
        out[track] = role
    if not out:
        raise NamingError("name at least one track, e.g. track3=surgeon")
    return out


def name_tracks(tracks: tuple[Trajectory, ...], names: dict[str, str]) -> list[Trajectory]:
    known = {t.name: t for t in tracks}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise NamingError(
            f"no {', '.join(unknown)} in the people file; it has "
            f"{', '.join(known)} ('egosurg people name FILE --list' shows where each stands)"
        )
    return [dataclasses.replace(known[t], name=role) for t, role in names.items()]


def write_roles(
    path: Path | str, people: TrajectoryFile, names: dict[str, str]
) -> list[Trajectory]:
    """The roles file for ``names`` (track -> role), with the people file's session: what
    ``egosurg people name`` and the viewer's "Name track" write, one format for both."""
    roles = name_tracks(people.trajectories, parse_names([f"{t}={r}" for t, r in names.items()]))
    write_trajectories(Path(path), roles, people.session)
    return roles


def names_in(
    roles: tuple[Trajectory, ...], tracks: tuple[Trajectory, ...], path: str
) -> dict[str, str]:
    """The names a roles file written from these tracks gives them (track -> role): each role is
    the track whose keyframes and gaps it carries. A role that is no track of the people file
    (the sim's truth, a path drawn by hand) is refused in one line: names written for these
    tracks would replace it."""
    out: dict[str, str] = {}
    for role in roles:
        same = [t.name for t in tracks if (t.keyframes, t.gaps_s) == (role.keyframes, role.gaps_s)]
        if not same:
            raise NamingError(
                f"{path} holds {role.name!r}, which is no track of the people file: names go to "
                "a roles file made from its tracks; give a new file (--roles NEW.toml)"
            )
        out[same[0]] = role.name
    return out


def describe(track: Trajectory) -> str:
    """One line: where the track stands (median eye), from when to when, how sure."""
    eyes = np.array([k.eye_m for k in track.keyframes])
    x, y, z = np.median(eyes, axis=0)
    conf = [k.confidence for k in track.keyframes if k.confidence is not None]
    t0, t1 = track.span_s
    sure = f", confidence {np.mean(conf):.2f}" if conf else ""
    gaps = f", {len(track.gaps_s)} gap(s)" if track.gaps_s else ""
    return (
        f"{track.name}: {t0:.1f}-{t1:.1f} s, {len(track.keyframes)} keyframes, mostly at "
        f"x {x:+.2f} y {y:+.2f} m, eye {z:.2f} m{sure}{gaps}"
    )


def suggest(tracks: tuple[Trajectory, ...]) -> list[str]:
    """Suggestions from the room, labelled as such, from where each track mostly stands: at the
    table's long sides, at its ends, away from it, or walking across the room; the table is
    taken to stand at the world's origin, its length along x (the rig is calibrated around it).
    They are guesses from position alone."""
    if not tracks:
        return []
    med = {t.name: np.median(np.array([k.eye_m for k in t.keyframes]), axis=0) for t in tracks}
    lines = []
    for t in tracks:
        x, y, _ = med[t.name]
        moved = np.ptp(np.array([k.eye_m for k in t.keyframes])[:, :2], axis=0).max()
        if moved > 2.0:
            guess = "a circulating role (walks across the room)"
        elif abs(y) < 1.0 and abs(x) < 1.0:
            guess = "a scrubbed role at the table's side (surgeon, assistant, scrub nurse)"
        elif abs(x) >= 1.0 and abs(y) < 1.0:
            guess = "at the table's end (anaesthetist at the head, or a bedside assistant)"
        else:
            guess = "away from the table (circulating, or at the back table)"
        lines.append(f"{t.name}: suggestion, not an identity: {guess}")
    return lines
