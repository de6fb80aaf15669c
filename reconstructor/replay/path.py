"""A trajectory as a camera at any time: positions on a cubic spline through the keyframes'
eyes, orientations by spherical linear interpolation (slerp), field of view linearly.

A natural cubic spline (scipy) passes through every keyframe with a continuous velocity and
acceleration, so a replay does not jerk at keyframes; slerp turns at a constant rate between
two keyframes along the shortest arc.

A trajectory's gaps (``gaps_s``: an estimated person hidden from every camera, or between two
tracks joined as one role) are kept: ``gap_at`` says whether a time lies inside one, where the
spline's eye is no one's, and replay and sightline show no view from there.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from protocol.camera import Camera, Intrinsics, Pose
from protocol.formats.trajectory import TIME_RESOLUTION_S, Trajectory
from reconstructor.errors import TrajectoryTimeError


class CameraPath:
    def __init__(self, trajectory: Trajectory) -> None:
        self.name = trajectory.name
        self.gaps_s = trajectory.gaps_s
        keys = trajectory.keyframes
        self.times_s = np.array([k.time_s for k in keys])
        poses = [k.pose() for k in keys]
        eyes = np.array([p.centre_m for p in poses])
        self._fov = np.array([k.fov_deg for k in keys])
        # world-from-camera rotations: slerp between them
        rots = Rotation.from_matrix(np.stack([p.R.T for p in poses]))
        if len(keys) == 1:
            self._eye = lambda t: eyes[0]
            self._rot = lambda t: rots[0]
        else:
            spline = CubicSpline(self.times_s, eyes, bc_type="natural")
            slerp = Slerp(self.times_s, rots)
            self._eye = spline
            self._rot = slerp

    @property
    def span_s(self) -> tuple[float, float]:
        return float(self.times_s[0]), float(self.times_s[-1])

    def require_inside(self, t_s: float, what: str = "time") -> None:
        t0, t1 = self.span_s
        if not (t0 - TIME_RESOLUTION_S <= t_s <= t1 + TIME_RESOLUTION_S):
            raise TrajectoryTimeError(
                f"{what} {t_s:.3f} s is outside trajectory {self.name!r}'s keyframes "
                f"({t0:.3f} s to {t1:.3f} s)"
            )

    def gap_at(self, t_s: float) -> tuple[float, float] | None:
        """The gap ``t_s`` lies inside (its ends are keyframes: seen), or None."""
        return next(((a, b) for a, b in self.gaps_s if a < t_s < b), None)

    def pose(self, t_s: float) -> Pose:
        self.require_inside(t_s)
        t = float(np.clip(t_s, *self.span_s))
        R_wc = np.asarray(self._rot(t).as_matrix()).reshape(3, 3)
        eye = np.asarray(self._eye(t), dtype=np.float64).reshape(3)
        R = R_wc.T
        return Pose(R=R, t_m=-R @ eye)

    def fov_deg(self, t_s: float) -> float:
        return float(np.interp(t_s, self.times_s, self._fov))

    def camera(self, t_s: float, size_px: tuple[int, int], eye_shift_m: np.ndarray | None = None):
        """The camera at ``t_s``; ``eye_shift_m`` (world metres) moves the eye, keeping the
        direction it looks in (a counterfactual position)."""
        pose = self.pose(t_s)
        if eye_shift_m is not None:
            centre = pose.centre_m + np.asarray(eye_shift_m, dtype=np.float64)
            pose = Pose(R=pose.R, t_m=-pose.R @ centre)
        intr = Intrinsics.from_fov(size_px[0], size_px[1], self.fov_deg(t_s))
        return Camera(name=self.name, intrinsics=intr, pose=pose)
