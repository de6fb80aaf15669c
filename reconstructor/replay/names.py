"""Tracks named as roles: ``egosurg people name people.toml track3=surgeon ...`` writes the roles
file the review tools read (``--roles``): the named tracks only, renamed, with their confidences,
gaps and session. Suggestions from the room (``suggest``) are printed as suggestions, never
written as names: where a track stands says what it may be, not who it is.

A person lost behind the table comes back as a new track, so one role may take several tracks
(``track3=surgeon track7=surgeon``): the role is their keyframes joined in time order, each
track's own gaps kept, and the time from one track's last keyframe to the next one's first
written as a gap too (``gaps_s``: nobody followed the person there; replay and sightline show no
view from inside a gap). Tracks of one role that share any instant (one starts at or before the
other's last keyframe) are refused: one person is one track at a time, and a second track
beside someone is someone else, or noise.

Here, in replay/, not in people/: the viewer names tracks too (``view_people.py``), and people/
comes after replay/ in the reconstructor's parts (tests/test_package_rules.py); both the
``egosurg people name`` command and the viewer write through ``write_roles``.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np

from protocol.formats.trajectory import Trajectory, TrajectoryFile, write_trajectories
from reconstructor.errors import CaseReplayError


class NamingError(CaseReplayError, ValueError):
    """Names that cannot be given; the message says which and what to write instead."""


_PAIR = re.compile(r"^(track\d+)=([A-Za-z0-9_-]+)$")


def parse_names(pairs: list[str]) -> dict[str, str]:
    """``["track3=surgeon", "track7=surgeon"]`` -> ``{"track3": "surgeon", "track7":
    "surgeon"}`` (track -> role; a role may take several tracks); one line naming a bad pair."""
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
        out[track] = role
    if not out:
        raise NamingError("name at least one track, e.g. track3=surgeon")
    return out


def _span(t0_s: float, t1_s: float) -> str:
    return f"at {t0_s:.1f} s" if t0_s == t1_s else f"{t0_s:.1f}-{t1_s:.1f} s"


def join_tracks(role: str, tracks: list[Trajectory]) -> Trajectory:
    """One role from its tracks, in time order: keyframes joined, each track's gaps kept and the
    hand-over from one track's last keyframe to the next one's first a gap. Tracks that share
    an instant are refused in one line naming both and the seconds they share."""
    order = sorted(tracks, key=lambda t: t.span_s)
    gaps = list(order[0].gaps_s)
    for a, b in itertools.pairwise(order):
        (a0, a1), (b0, b1) = a.span_s, b.span_s
        if b0 <= a1:
            raise NamingError(
                f"{a.name} ({_span(a0, a1)}) and {b.name} ({_span(b0, b1)}) are both named "
                f"{role!r} but overlap {_span(b0, min(a1, b1))}: one person is one track at a "
                "time; give this role only one of them"
            )
        gaps += [(a1, b0), *b.gaps_s]
    keys = tuple(k for t in order for k in t.keyframes)
    return Trajectory(name=role, keyframes=keys, gaps_s=tuple(gaps))


def name_tracks(tracks: tuple[Trajectory, ...], names: dict[str, str]) -> list[Trajectory]:
    """The roles ``names`` (track -> role) gives, in the order the roles are first named."""
    known = {t.name: t for t in tracks}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise NamingError(
            f"no {', '.join(unknown)} in the people file; it has "
            f"{', '.join(known)} ('egosurg people name FILE --list' shows where each stands)"
        )
    roles = dict.fromkeys(names.values())
    return [join_tracks(r, [known[t] for t, n in names.items() if n == r]) for r in roles]


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
    the join of the tracks whose keyframes it carries, and joining them again gives its
    keyframes and gaps. A role that is no join of tracks of the people file (the sim's truth, a
    path drawn by hand) is refused in one line: names written for these tracks would replace
    it."""
    out: dict[str, str] = {}
    for role in roles:
        keys = set(role.keyframes)
        mine = [t for t in tracks if keys.issuperset(t.keyframes)]
        joined = None
        if mine:
            try:
                joined = join_tracks(role.name, mine)
            except NamingError:
                joined = None
        if joined is None or (joined.keyframes, joined.gaps_s) != (role.keyframes, role.gaps_s):
            raise NamingError(
                f"{path} holds {role.name!r}, which is no track of the people file: names go to "
                "a roles file made from its tracks; give a new file (--roles NEW.toml)"
            )
        out.update({t.name: role.name for t in mine})
    return out


def role_lines(names: dict[str, str], tracks: tuple[Trajectory, ...]) -> list[str]:
    """Per role, the tracks it joins and the hand-overs between them: ``surgeon = track2 +
    track7: 2.0-54.0 s, not followed 13.5-15.0 s``."""
    known = {t.name: t for t in tracks}
    lines = []
    for role in dict.fromkeys(names.values()):
        mine = sorted((known[t] for t, r in names.items() if r == role), key=lambda t: t.span_s)
        t0, t1 = mine[0].span_s[0], mine[-1].span_s[1]
        hand = [f"{a.span_s[1]:.1f}-{b.span_s[0]:.1f}" for a, b in itertools.pairwise(mine)]
        between = f", not followed {', '.join(hand)} s (between tracks)" if hand else ""
        joins = " + ".join(t.name for t in mine)
        lines.append(f"{role} = {joins}: {t0:.1f}-{t1:.1f} s{between}")
    return lines


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
