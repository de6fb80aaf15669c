"""The demo's naming of the tracks ``egosurg people`` found: by the simulator's truth, for the
demo only.

On a real case a reviewer names the tracks (``egosurg people name FILE --list --suggest``, or
``egosurg view --people``). The demo has no reviewer, so it gives each track the name of the
person whose true eye (``World.head_poses``, at the sim time whose picture the cameras showed:
the sim rig's content loops and changes once a second, ``sim.timing.content_time_s``) is nearest
the track's eye, median over the track's keyframes, nearest pairs first and only within
``MAX_NAMING_M`` (the distance bench/bench_people.py matches within). Each track takes one
person; a person may take several tracks (someone lost behind the table comes back as a new
track), as a reviewer would name them, as long as they do not overlap in time (one person is
one track at a time: ``reconstructor.replay.names.join_tracks``). The roles file itself is then
written by ``egosurg people name``, as a reviewer's would be: the tracks' estimated keyframes
joined under the person's name, the time between them a gap, never the truth's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.formats.trajectory import Trajectory, read_trajectories

MAX_NAMING_M = 0.5

TrueEyes = Callable[[float], dict[str, np.ndarray]]  # case time, s -> person -> eye (3,), m


@dataclass(frozen=True)
class TruthName:
    track: str
    role: str
    median_m: float  # the track's eye to the person's true eye, median over its keyframes


def median_distances_m(track: Trajectory, true_eyes: TrueEyes) -> dict[str, float]:
    """Person -> the track's eye to that person's true eye, median over the track's keyframes
    (a person not in the room at one of them counts as infinitely far there)."""
    per: dict[str, list[float]] = {}
    eyes = [true_eyes(k.time_s) for k in track.keyframes]
    for name in {n for e in eyes for n in e}:
        per[name] = [
            float(np.linalg.norm(np.subtract(k.eye_m, e[name]))) if name in e else np.inf
            for k, e in zip(track.keyframes, eyes, strict=True)
        ]
    return {name: float(np.median(d)) for name, d in per.items()}


def _overlap(a: Trajectory, b: Trajectory) -> bool:
    """The two tracks share an instant (the rule ``egosurg people name`` refuses)."""
    return a.span_s[0] <= b.span_s[1] and b.span_s[0] <= a.span_s[1]


def name_by_truth(
    people: Path, true_eyes: TrueEyes, max_m: float = MAX_NAMING_M
) -> list[TruthName]:
    """Tracks of the people file ``people`` named after the sim's people: each track at most
    once, a person's tracks never overlapping in time."""
    tracks = {t.name: t for t in read_trajectories(people)}
    pairs = sorted(
        (d, name, role)
        for name, t in tracks.items()
        for role, d in median_distances_m(t, true_eyes).items()
    )
    named: list[TruthName] = []
    for d, track, role in pairs:
        if d > max_m:
            break
        if any(n.track == track for n in named):
            continue
        if not any(n.role == role and _overlap(tracks[n.track], tracks[track]) for n in named):
            named.append(TruthName(track, role, d))
    return named


def covering(
    named: list[TruthName], people: Path, case_times_s: list[float], min_timestamps: int = 2
) -> list[str]:
    """The named roles whose tracks span at least ``min_timestamps`` of the case's timestamps
    (replay and sightline show the case where the role's eye is known: inside one of its
    tracks, not between two), most first, then the longest tracks."""
    tracks = {t.name: t for t in read_trajectories(people)}
    out = []
    for role in dict.fromkeys(n.role for n in named):
        spans = [tracks[n.track].span_s for n in named if n.role == role]
        inside = sum(any(a - 1e-6 <= t <= b + 1e-6 for a, b in spans) for t in case_times_s)
        if inside >= min_timestamps:
            out.append((inside, sum(b - a for a, b in spans), role))
    return [role for *_, role in sorted(out, reverse=True)]
