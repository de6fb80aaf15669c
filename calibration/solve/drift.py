"""How far each camera moved between two calibrations of the same rig.

Two wand solves of one rig agree only up to a rigid motion of the whole rig (each picks its own
world frame), so the new calibration is first moved onto the old one: the rotation and
translation that best map its camera centres onto the old ones (Kabsch). A least-squares fit
over *every* camera would let a camera that really moved pull the others with it: one camera of
four moved by 12 mm leaves about 3 mm on each of the three that stayed, enough, with the solve's
own noise, to push one of them past the drift limit. So the fit is robust, camera by camera:
after each fit, the camera that sits furthest from its old place is left out of the next fit if
it is past ``outlier_mm``, for as long as the cameras still in the fit are a strict majority of
the rig (and at least two). The drift of every camera, including those left out, is then
measured in the frame the others agree on.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration


@dataclass(frozen=True)
class Drift:
    """``aligned``: the new calibration in the old one's world frame. Per sensor of ``aligned``,
    ``rotation_deg`` and ``position_mm``: the change from the old calibration.
    ``fitted_serials``: the cameras the alignment was fitted on (the others moved)."""

    aligned: RigCalibration
    rotation_deg: np.ndarray
    position_mm: np.ndarray
    fitted_serials: tuple[int, ...]


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising sum |R a_i + t - b_i|^2 over the rows of ``a`` and ``b`` (N, 3)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def align_to(new: RigCalibration, old: RigCalibration, outlier_mm: float = 5.0) -> Drift:
    """Express ``new`` in ``old``'s world frame, fitted on the cameras that did not move (module
    docstring). Sensors are matched by camera serial and side."""
    pairs = [(s, old.sensor(s.camera_serial, s.side)) for s in new.sensors]
    a = np.array([s.pose.centre_m for s, _ in pairs])
    b = np.array([o.pose.centre_m for _, o in pairs])
    serial = np.array([s.camera_serial for s, _ in pairs])
    cameras = list(dict.fromkeys(serial.tolist()))
    fitted = list(cameras)
    while True:
        rows = np.isin(serial, fitted)
        R, t = kabsch(a[rows], b[rows])  # x_old = R @ x_new + t
        off_mm = 1000 * np.linalg.norm(a @ R.T + t - b, axis=1)
        per_camera = {c: float(off_mm[serial == c].max()) for c in fitted}
        worst = max(per_camera, key=lambda c: per_camera[c])
        can_drop = len(fitted) - 1 > len(cameras) / 2 and len(fitted) - 1 >= 2
        if per_camera[worst] <= outlier_mm or not can_drop:
            break
        fitted.remove(worst)
    sensors, rot_deg, pos_mm = [], [], []
    for s, o in pairs:
        Rc = s.pose.R @ R.T
        pose = Pose(R=Rc, t_m=s.pose.t_m - Rc @ t)
        sensors.append(dataclasses.replace(s, pose=pose))
        dR = pose.R @ o.pose.R.T
        rot_deg.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
        pos_mm.append(1000 * np.linalg.norm(pose.centre_m - o.pose.centre_m))
    aligned = RigCalibration(
        sensors=tuple(sensors),
        resolution=new.resolution,
        world_frame=old.world_frame,
        quality=new.quality,
        metadata=new.metadata,
    )
    return Drift(aligned, np.array(rot_deg), np.array(pos_mm), tuple(int(c) for c in fitted))
