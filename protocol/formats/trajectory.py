"""Viewpoints through space and time: the trajectory / roles TOML file (``egosurg-trajectories``).

One file holds one or more named trajectories. A role file (``egosurg sim roles`` writes one
from the simulator's true head poses) holds one per person; a replay trajectory file holds one.
Times are case time: seconds since the session started, as in the case index (``t_s``).

Format (version 1)::

    format = "egosurg-trajectories"
    format_version = 1

    [session]                           # the session it was made for (optional; see below)
    name = "sim-intraoperative-seed3"
    started_unix_ns = 1767225600000000000

    [[trajectories]]
    name = "surgeon"                    # a role's name, or any name for a path
    [[trajectories.keyframes]]
    time_s = 2.0
    eye_m = [0.4, -0.6, 1.7]            # the eye (camera centre), world metres
    look_at_m = [0.1, 0.0, 1.0]         # a point it looks at (image up towards +z) ...
    # orientation_wxyz = [w, x, y, z]   # ... or the world-from-camera rotation (OpenCV axes)
    fov_deg = 90.0                      # horizontal field of view
    # confidence = 0.93                 # optional, 0..1: how sure an estimate is (egosurg people)
    # gaps_s = [[12.0, 14.5]]           # optional, in [[trajectories]]: spans the person was hidden

An estimated trajectory (``egosurg people``) marks each keyframe's ``confidence`` and the spans
in which the person was seen by no camera (``gaps_s``: the last keyframe before, the first
after); a role joined from several tracks has the time between them as gaps too. Replay and
sightline show no view and give no answer from inside a gap: nobody knows where that eye was.

``[session]`` names the recording the times belong to (``protocol/formats/session_id.py``):
the review commands refuse a file made for another session than the case's, and warn about one
without the table (written by hand, or by an egosurg before it existed).

Shared by sim/ (which writes true roles) and reconstructor/ (which replays them): a contract,
so it lives here and imports neither.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.camera import Pose
from protocol.durable import atomic_write_bytes
from protocol.errors import UserError
from protocol.formats.session_id import SessionId, session_toml_lines
from protocol.toml_config import load_toml, read_table

TRAJECTORY_FORMAT = "egosurg-trajectories"
TRAJECTORY_FORMAT_VERSION = 1
# Times are written to the microsecond (six decimals, below), so a keyframe made at a case
# timestamp (a set time in nanoseconds) reads back up to half of this away from it: a time
# within this of a trajectory's first or last keyframe is at that keyframe, not outside it.
TIME_RESOLUTION_S = 1e-6


class TrajectoryFileError(UserError, ValueError):
    """A trajectory or roles file that cannot be used; the message names the entry and the fix."""


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    out = np.asarray(q) / np.linalg.norm(q)
    return -out if out[0] < 0 else out


def matrix_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True, kw_only=True)
class Keyframe:
    time_s: float
    eye_m: tuple[float, float, float]
    look_at_m: tuple[float, float, float] | None = None
    orientation_wxyz: tuple[float, float, float, float] | None = None  # world-from-camera
    fov_deg: float = 90.0
    confidence: float | None = None  # 0..1 for an estimate; None: given (truth, or by hand)

    def __post_init__(self) -> None:
        if self.confidence is not None and not 0.0 <= self.confidence <= 1.0:
            raise ValueError(f"confidence {self.confidence} must be between 0 and 1")
        if (self.look_at_m is None) == (self.orientation_wxyz is None):
            raise ValueError("give exactly one of look_at_m and orientation_wxyz")
        if not math.isfinite(self.time_s):
            raise ValueError(f"time_s {self.time_s} must be a finite number of seconds")
        if not 1.0 < self.fov_deg < 179.0:
            raise ValueError(f"fov_deg {self.fov_deg} must be between 1 and 179 degrees")
        if not np.all(np.isfinite(self.eye_m)):
            raise ValueError(f"eye_m {self.eye_m} must be three finite numbers")
        if (
            self.look_at_m is not None
            and np.linalg.norm(np.subtract(self.look_at_m, self.eye_m)) < 1e-6
        ):
            raise ValueError("look_at_m must differ from eye_m")
        if self.orientation_wxyz is not None and not (
            np.all(np.isfinite(self.orientation_wxyz)) and np.linalg.norm(self.orientation_wxyz)
        ):
            raise ValueError(
                f"orientation_wxyz {self.orientation_wxyz} must be a non-zero quaternion"
            )

    def pose(self) -> Pose:
        """World-to-camera pose (OpenCV axes)."""
        eye = np.asarray(self.eye_m, dtype=np.float64)
        if self.look_at_m is not None:
            return Pose.look_at(eye, np.asarray(self.look_at_m, dtype=np.float64))
        R = matrix_from_quat_wxyz(np.asarray(self.orientation_wxyz)).T
        return Pose(R=R, t_m=-R @ eye)

    @classmethod
    def from_pose(cls, time_s: float, pose: Pose, fov_deg: float) -> Keyframe:
        quat = quat_wxyz_from_matrix(pose.R.T)
        return cls(
            time_s=float(time_s),
            eye_m=tuple(float(v) for v in pose.centre_m),  # type: ignore[arg-type]
            orientation_wxyz=tuple(float(v) for v in quat),  # type: ignore[arg-type]
            fov_deg=float(fov_deg),
        )


@dataclass(frozen=True, kw_only=True)
class Trajectory:
    name: str
    keyframes: tuple[Keyframe, ...]
    gaps_s: tuple[tuple[float, float], ...] = ()  # hidden from every camera: (from, to)

    def __post_init__(self) -> None:
        for gap in self.gaps_s:
            if len(gap) != 2 or not gap[0] < gap[1]:
                raise ValueError(f"gap {list(gap)} must be [from, to] seconds with from < to")
        if not self.name or not self.name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"name {self.name!r}: use letters, digits, '-' or '_'")
        if not self.keyframes:
            raise ValueError(f"trajectory {self.name!r} has no keyframes")
        times = [k.time_s for k in self.keyframes]
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"trajectory {self.name!r}: keyframe times must strictly increase")

    @property
    def span_s(self) -> tuple[float, float]:
        return self.keyframes[0].time_s, self.keyframes[-1].time_s


@dataclass(frozen=True, kw_only=True)
class TrajectoryFile:
    format: str
    format_version: int
    session: SessionId | None = None  # the session it was made for; None: not recorded
    trajectories: tuple[Trajectory, ...] = ()


def read_trajectories(path: Path | str) -> tuple[Trajectory, ...]:
    """All trajectories of a file; every problem is a :class:`TrajectoryFileError`."""
    return read_trajectory_file(path).trajectories


def read_trajectory_file(path: Path | str) -> TrajectoryFile:
    """The whole file: its trajectories and the session it names (``session``)."""
    path = Path(path)
    if not path.exists():
        raise TrajectoryFileError(f"the trajectory file {path} does not exist")
    table, _ = load_toml(path, "the trajectory file", error=TrajectoryFileError)
    if table.get("format") != TRAJECTORY_FORMAT:
        raise TrajectoryFileError(
            f'{path} is not a trajectory file: it needs format = "{TRAJECTORY_FORMAT}" '
            "(docs/replay.md has an example)"
        )
    if table.get("format_version") != TRAJECTORY_FORMAT_VERSION:
        raise TrajectoryFileError(
            f"{path} has format_version {table.get('format_version')!r}; this egosurg reads "
            f"{TRAJECTORY_FORMAT_VERSION}"
        )
    file = read_table(TrajectoryFile, table, str(path), error=TrajectoryFileError)
    out = file.trajectories
    if not out:
        raise TrajectoryFileError(f"{path} holds no [[trajectories]]")
    names = [t.name for t in out]
    if len(set(names)) != len(names):
        raise TrajectoryFileError(f"{path}: trajectory names repeat: {names}")
    return file


def _fmt(values: tuple[float, ...] | None) -> str:
    return "[" + ", ".join(f"{v:.6f}" for v in values or ()) + "]"


def trajectories_toml(
    trajectories: tuple[Trajectory, ...] | list[Trajectory], session: SessionId | None = None
) -> str:
    lines = [f'format = "{TRAJECTORY_FORMAT}"', f"format_version = {TRAJECTORY_FORMAT_VERSION}"]
    lines += session_toml_lines(session)
    for tr in trajectories:
        lines += ["", "[[trajectories]]", f'name = "{tr.name}"']
        if tr.gaps_s:
            lines.append("gaps_s = [" + ", ".join(_fmt(g) for g in tr.gaps_s) + "]")
        for k in tr.keyframes:
            lines += ["[[trajectories.keyframes]]", f"time_s = {k.time_s:.6f}"]
            lines.append(f"eye_m = {_fmt(k.eye_m)}")
            if k.look_at_m is not None:
                lines.append(f"look_at_m = {_fmt(k.look_at_m)}")
            else:
                lines.append(f"orientation_wxyz = {_fmt(k.orientation_wxyz)}")
            lines.append(f"fov_deg = {k.fov_deg:g}")
            if k.confidence is not None:
                lines.append(f"confidence = {k.confidence:.3f}")
    return "\n".join(lines) + "\n"


def write_trajectories(
    path: Path | str,
    trajectories: tuple[Trajectory, ...] | list[Trajectory],
    session: SessionId | None = None,
) -> Path:
    """Write the file; ``session``: the session it is made for (its ``[session]`` table). A
    reader (a review tool, while the viewer names a track) sees the old file or the whole new
    one, never a torn one; a file rewritten keeps its permissions."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = path.stat().st_mode & 0o777 if path.exists() else None
    atomic_write_bytes(path, trajectories_toml(trajectories, session).encode(), mode=mode)
    return path
