"""What the browser viewer (``egosurg view``, :mod:`reconstructor.replay.view`) is handed: our
splats as viser's Gaussians, our cameras as viser's, and viser's camera back as a keyframe.

No viser import here: these are the conversions, tested on their own.

**Splats.** Viser draws each Gaussian from its centre, its 3x3 covariance, an RGB colour and an
opacity (antimatter15's layout: the covariance's six upper terms as float16, colour and opacity
as bytes). Ours are raw 3DGS parameters (``reconstructor/splats/gaussians.py``), so
``covariance = R S S Rᵀ`` with R from the normalised quaternion (w, x, y, z) and S = diag(exp
(log_scales)), ``rgb = 0.5 + C0 · sh_dc`` (degree 0: the view-dependent terms are dropped; the
paper trains degree 0), ``opacity = sigmoid(logit)``.

float16 has ten bits of mantissa and stops being normal below 6.1e-5: in square metres that is
a Gaussian of 7.8 mm standard deviation, and trained models hold many of 1-5 mm, whose
variances would lose most of their digits. So viser gets the scene in decimetres
(``VIEWER_UNIT_M``) and draws the node scaled by 0.1 (its shader applies the node's scale to
centres and covariances alike): every Gaussian down to 0.8 mm stays a normal float16, and the
largest one that fits is 25 m.

**Cameras.** Our poses are world-to-camera with OpenCV axes (x right, y down, z forward), as are
viser's (``wxyz`` is R_world_camera, +z looks, -y is up). Our field of view is horizontal
(``Intrinsics.from_fov``); viser's is vertical, in radians.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.camera import Pose
from protocol.formats.session_id import SessionId
from protocol.formats.site import SiteBox
from protocol.formats.trajectory import (
    Keyframe,
    Trajectory,
    TrajectoryFileError,
    matrix_from_quat_wxyz,
    quat_wxyz_from_matrix,
    read_trajectories,
    write_trajectories,
)
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)

VIEWER_UNIT_M = 0.1  # the scene goes to viser in decimetres (module docstring)
_FLOAT16_MAX = 65504.0


@dataclass(frozen=True)
class SplatArrays:
    """N Gaussians as viser takes them, in metres: centres (N, 3), covariances (N, 3, 3) m²,
    rgbs (N, 3) in [0, 1], opacities (N, 1) in [0, 1]; all float32."""

    centers_m: np.ndarray
    covariances_m2: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray

    @property
    def num(self) -> int:
        return int(self.centers_m.shape[0])


def splat_arrays(g: Gaussians) -> SplatArrays:
    q = g.quats_wxyz.detach().cpu().double().numpy()
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )  # (N, 3, 3), rows of each rotation
    s2 = np.exp(2.0 * g.log_scales.detach().cpu().double().numpy())  # variances on local axes
    cov = np.einsum("nij,nj,nkj->nik", R, s2, R)
    return SplatArrays(
        centers_m=g.means_m.detach().cpu().numpy().astype(np.float32),
        covariances_m2=cov.astype(np.float32),
        rgbs=np.clip(g.colors().detach().cpu().numpy(), 0.0, 1.0).astype(np.float32),
        opacities=g.opacities().detach().cpu().numpy().astype(np.float32)[:, None],
    )


def in_viewer_units(s: SplatArrays) -> dict[str, np.ndarray]:
    """Keyword arguments for ``scene.add_gaussian_splats`` (with ``scale=VIEWER_UNIT_M``):
    centres and covariances in decimetres, the covariances clipped into float16's range,
    colours and opacities as bytes."""
    k = 1.0 / VIEWER_UNIT_M
    cov = s.covariances_m2 * np.float32(k * k)
    big = np.abs(cov) > _FLOAT16_MAX
    if big.any():
        log.warning(
            "%d Gaussians are larger than 25 m: drawn clipped", int(big.any(axis=(1, 2)).sum())
        )
        cov = np.clip(cov, -_FLOAT16_MAX, _FLOAT16_MAX)
    return {
        "centers": s.centers_m * np.float32(k),
        "covariances": cov,
        # bytes rounded here: viser truncates floats (x 255), a grey level darker on average
        "rgbs": _to_byte(s.rgbs),
        "opacities": _to_byte(s.opacities),
    }


def _to_byte(values: np.ndarray) -> np.ndarray:
    return (np.clip(values, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def vfov_rad(hfov_deg: float, aspect: float) -> float:
    """Vertical field of view (viser's, radians) of a horizontal one (ours, degrees)."""
    return 2.0 * math.atan(math.tan(math.radians(hfov_deg) / 2.0) / aspect)


def hfov_deg(vfov: float, aspect: float) -> float:
    return math.degrees(2.0 * math.atan(math.tan(vfov / 2.0) * aspect))


@dataclass(frozen=True)
class ViserCamera:
    """A camera as viser's orbit controls take it: eye, a point looked at, image up, vertical
    field of view (radians)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov_rad: float

    @property
    def wxyz(self) -> np.ndarray:
        """R_world_camera (OpenCV axes) as a quaternion: what viser's frustums take."""
        z = self.look_at - self.position
        z = z / np.linalg.norm(z)
        x = np.cross(-self.up, z)
        x = x / np.linalg.norm(x)
        return quat_wxyz_from_matrix(np.stack([x, np.cross(z, x), z], axis=1))


def viser_camera(pose: Pose, hfov: float, aspect: float, distance_m: float = 1.0) -> ViserCamera:
    """Our world-to-camera pose as viser's; ``look_at`` is ``distance_m`` ahead (where the
    orbit controls turn about)."""
    eye = pose.centre_m
    return ViserCamera(
        position=eye,
        look_at=eye + distance_m * pose.R[2],
        up=-pose.R[1],
        fov_rad=vfov_rad(hfov, aspect),
    )


def pose_from_viser(wxyz: np.ndarray, position: np.ndarray) -> Pose:
    """Viser's camera (R_world_camera as w, x, y, z, and the eye) as our world-to-camera pose."""
    R = matrix_from_quat_wxyz(np.asarray(wxyz, dtype=np.float64)).T
    return Pose(R=R, t_m=-R @ np.asarray(position, dtype=np.float64))


def box_wxyz(box: SiteBox) -> np.ndarray:
    """A site box's world-from-box rotation (its yaw about +z) as a quaternion."""
    return quat_wxyz_from_matrix(box.rotation)


def check_viewpoint_file(path: Path) -> None:
    """Refuse, at start, a ``--save-to`` that holds something other than trajectories: saving
    must never overwrite a file the user meant to keep."""
    if path.exists():
        if not path.is_file():
            raise TrajectoryFileError(f"--save-to {path} is a folder; give a .toml file path")
        read_trajectories(path)  # raises TrajectoryFileError with the reason
    elif not path.parent.is_dir():
        raise TrajectoryFileError(f"--save-to {path}: the folder {path.parent} does not exist")


def save_viewpoint(
    path: Path, name: str, keyframe: Keyframe, session: SessionId | None = None
) -> Trajectory:
    """Add ``keyframe`` to trajectory ``name`` in ``path`` (made if missing), replacing one at
    the same time; the file's other trajectories are kept, and ``session`` (the case's) goes in
    its ``[session]`` table. Returns the trajectory written."""
    others: list[Trajectory] = []
    keys: list[Keyframe] = []
    if path.exists():
        for tr in read_trajectories(path):
            if tr.name == name:
                keys = list(tr.keyframes)
            else:
                others.append(tr)
    keys = [k for k in keys if abs(k.time_s - keyframe.time_s) > 1e-6] + [keyframe]
    keys.sort(key=lambda k: k.time_s)
    trajectory = Trajectory(name=name, keyframes=tuple(keys))
    write_trajectories(path, [*others, trajectory], session=session)
    return trajectory
