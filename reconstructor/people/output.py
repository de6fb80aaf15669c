"""The people file: the trajectory file the review tools read (``egosurg-trajectories``), one
trajectory per track (``track1``, ``track2``, ...), each keyframe with its ``confidence``, each
track's ``gaps_s`` (hidden from every camera: not filled in), and the session it was made for."""

from __future__ import annotations

from pathlib import Path

from protocol.formats.session_id import SessionId
from protocol.formats.trajectory import Keyframe, Trajectory, write_trajectories
from reconstructor.people.config import PeopleConfig
from reconstructor.people.run import People

LOOK_AHEAD_M = 1.0


def trajectories(people: People, config: PeopleConfig) -> list[Trajectory]:
    out = []
    for tr in people.tracks:
        keys = tuple(
            Keyframe(
                time_s=p.time_s,
                eye_m=tuple(float(v) for v in p.eye_m),  # type: ignore[arg-type]
                look_at_m=tuple(float(v) for v in p.eye_m + LOOK_AHEAD_M * p.gaze()),  # type: ignore[arg-type]
                fov_deg=config.fov_deg,
                confidence=round(p.confidence, 3),
            )
            for p in people.poses[tr.id]
        )
        out.append(Trajectory(name=f"track{tr.id}", keyframes=keys, gaps_s=tuple(tr.gaps_s())))
    return out


def write_people(
    path: Path | str, people: People, config: PeopleConfig, session: SessionId | None
) -> Path:
    return write_trajectories(path, trajectories(people, config), session)
