"""Four simulated ZED X stereo cameras on the walls, with their factory calibration.

Each unit gets its own, slightly different factory intrinsics and stereo extrinsics (as real units
do), written as a real ``SN<serial>.conf``. The renderer reads every number from that model, so a
file written here and parsed back describes exactly the images the sim makes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from protocol.camera import Camera, Intrinsics, Pose, Resolution
from protocol.formats.zed_conf import ZedFactoryCalibration, derive_intrinsics
from sim.room import RoomSpec

ZEDX_FX_HD1200_PX = 740.0
ZEDX_BASELINE_MM = 120.0
# The ZED X housing, width (along the baseline) x height x depth (Stereolabs datasheet: 188 x 49
# x 47 mm): each sensor sits 34 mm in from the housing's end.
ZEDX_HOUSING_MM = (188.0, 49.0, 47.0)
MOUNT_MARGIN_M = 0.02  # every corner of a housing keeps this far from the walls, floor, ceiling

# (x, y, z) of the housing's centre (midway between the sensors) and the point the camera looks
# at; above head height, on the long walls, opposite the table, two per wall (as in the paper's
# Figure 1). 15 cm off the wall: the bracket's depth, and room for the housing at any jitter.
MOUNTS_M: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((1.9, 2.85, 2.45), (0.0, 0.0, 0.9)),
    ((-1.9, 2.85, 2.45), (0.0, 0.0, 0.9)),
    ((1.9, -2.85, 2.45), (0.0, 0.0, 0.9)),
    ((-1.9, -2.85, 2.45), (0.0, 0.0, 0.9)),
)
NODES = ("orin-a", "orin-a", "orin-b", "orin-b")

# One sensor of every rig has the 8-term rational lens model that Stereolabs gives ZED X lenses
# (OpenCV's CALIB_RATIONAL_MODEL: k1 k2 p1 p2 k3 k4 k5 k6), so calibration and reconstruction are
# tested against truth with it. Its denominator (k4 k5 k6) is fixed and ZED X-like; k1 k2 k3 are
# refitted so the lens images the scene as its drawn five-term twin does (within 1 px over the
# field): the rig's coverage, and so every truth test's bound, stay what they were, while any
# code that dropped k4..k6 would be off by tens of pixels.
RATIONAL_SENSOR = (0, "left")  # (unit index, side)
RATIONAL_K4_K6 = (0.3, 0.05, 0.02)
RATIONAL_FIT_MAX_R2 = 2.6  # squared normalized radius just past a ZED X HD1200 image's corners


@dataclass(frozen=True)
class ZedUnit:
    """One stereo camera: its factory file, which node reads it, and its left sensor's pose."""

    index: int
    serial: int
    node_id: str
    factory: ZedFactoryCalibration
    left_pose: Pose  # world-to-left-sensor

    def right_pose(self, resolution: Resolution | str = Resolution.HD1200) -> Pose:
        st = self.factory.stereo(resolution)
        return st.right_from_left.compose(self.left_pose)

    def sensor(self, side: str, resolution: Resolution | str) -> Camera:
        res = Resolution.parse(resolution)
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        table = self.factory.left if side == "left" else self.factory.right
        pose = self.left_pose if side == "left" else self.right_pose(res)
        return Camera(name=f"SN{self.serial}-{side}", intrinsics=table[res], pose=pose)


def rational_twin(dist: tuple[float, ...]) -> tuple[float, ...]:
    """The rational lens (``RATIONAL_K4_K6`` below k1 k2 k3, same p1 p2) nearest to a five-term
    one: num / den = the five-term radial factor, in least squares over the field."""
    r2 = np.linspace(0.0, RATIONAL_FIT_MAX_R2, 200)
    k1, k2, p1, p2, k3 = dist[:5]
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    k4, k5, k6 = RATIONAL_K4_K6
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    powers = np.column_stack([r2, r2**2, r2**3])
    (n1, n2, n3), *_ = np.linalg.lstsq(powers, radial * den - 1, rcond=None)
    return (round(float(n1), 6), round(float(n2), 6), p1, p2, round(float(n3), 6), k4, k5, k6)


def _factory(
    serial: int, rng: np.random.Generator, rational_side: str | None = None
) -> ZedFactoryCalibration:
    left: dict[Resolution, Intrinsics] = {}
    right: dict[Resolution, Intrinsics] = {}
    for side, table in (("left", left), ("right", right)):
        fx = ZEDX_FX_HD1200_PX + rng.uniform(-6, 6)
        base = Intrinsics(
            width_px=1920,
            height_px=1200,
            fx_px=round(fx, 4),
            fy_px=round(fx + rng.uniform(-0.6, 0.6), 4),
            cx_px=round(959.5 + rng.uniform(-5, 5), 4),
            cy_px=round(599.5 + rng.uniform(-5, 5), 4),
            dist=(
                round(-0.042 + rng.uniform(-0.004, 0.004), 6),
                round(0.018 + rng.uniform(-0.003, 0.003), 6),
                round(rng.uniform(-2e-4, 2e-4), 7),
                round(rng.uniform(-2e-4, 2e-4), 7),
                round(-0.004 + rng.uniform(-0.001, 0.001), 6),
            ),
        )
        if side == rational_side:  # drawn as the others are, so every other number stays
            base = replace(base, dist=rational_twin(base.dist))
        for res in Resolution:
            table[res] = derive_intrinsics(base, res)
    rot = tuple(round(float(v), 6) for v in rng.uniform(-0.003, 0.003, size=3))
    return ZedFactoryCalibration(
        serial=serial,
        left=left,
        right=right,
        baseline_mm=round(ZEDX_BASELINE_MM + rng.uniform(-0.5, 0.5), 4),
        ty_mm=round(rng.uniform(-0.2, 0.2), 4),
        tz_mm=round(rng.uniform(-0.3, 0.3), 4),
        rodrigues_rad={res: rot for res in Resolution},  # type: ignore[misc]
    )


def build_rig(seed: int, room: RoomSpec) -> tuple[ZedUnit, ...]:
    """The four units of ``seed``'s rig; each whole housing inside ``room`` (``MOUNT_MARGIN_M``).

    Raises ``OutsideRoomError`` when a housing does not fit (a mount too near a wall).
    """
    rng = np.random.default_rng([seed, 0x21C])
    units = []
    for i, ((mount, target), node) in enumerate(zip(MOUNTS_M, NODES, strict=True)):
        serial = 41_000_000 + int(rng.integers(100_000, 999_999)) * 10 + i
        centre = np.asarray(mount) + rng.uniform(-0.05, 0.05, size=3)
        target_a = np.asarray(target) + rng.uniform(-0.15, 0.15, size=3)
        factory = _factory(serial, rng, RATIONAL_SENSOR[1] if i == RATIONAL_SENSOR[0] else None)
        facing = Pose.look_at(centre, target_a)
        for corner in housing_corners_m(centre, facing.R):
            room.require_inside(corner, f"the housing of camera SN{serial}", MOUNT_MARGIN_M)
        left_centre = centre - factory.baseline_mm / 2000.0 * facing.R[0]  # x: toward the right
        units.append(
            ZedUnit(
                index=i,
                serial=serial,
                node_id=node,
                factory=factory,
                left_pose=Pose(R=facing.R, t_m=-facing.R @ left_centre),
            )
        )
    return tuple(units)


def housing_corners_m(centre_m: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(8, 3) world corners of a ZED X housing centred at ``centre_m`` with camera axes ``R``."""
    half = np.asarray(ZEDX_HOUSING_MM) / 2000.0
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return np.asarray(centre_m) + (signs * half) @ np.asarray(R)
