"""Four simulated ZED X stereo cameras on the walls, with their factory calibration.

Each unit gets its own, slightly different factory intrinsics and stereo extrinsics (as real units
do), written as a real ``SN<serial>.conf``. The renderer reads every number from that model, so a
file written here and parsed back describes exactly the images the sim makes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.camera import Camera, Intrinsics, Pose, Resolution
from protocol.zed_conf import ZedFactoryCalibration, derive_intrinsics
from sim.room import RoomSpec

ZEDX_FX_HD1200_PX = 740.0
ZEDX_BASELINE_MM = 120.0

# (x, y, z) of the left sensor and the point it looks at; above head height, on the long walls,
# opposite the table, two per wall (as in the paper's Figure 1).
MOUNTS_M: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((1.9, 2.88, 2.45), (0.0, 0.0, 0.9)),
    ((-1.9, 2.88, 2.45), (0.0, 0.0, 0.9)),
    ((1.9, -2.88, 2.45), (0.0, 0.0, 0.9)),
    ((-1.9, -2.88, 2.45), (0.0, 0.0, 0.9)),
)
NODES = ("orin-a", "orin-a", "orin-b", "orin-b")


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


def _factory(serial: int, rng: np.random.Generator) -> ZedFactoryCalibration:
    left: dict[Resolution, Intrinsics] = {}
    right: dict[Resolution, Intrinsics] = {}
    for table in (left, right):
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
    rng = np.random.default_rng([seed, 0x21C])
    units = []
    for i, ((eye, target), node) in enumerate(zip(MOUNTS_M, NODES, strict=True)):
        serial = 41_000_000 + int(rng.integers(100_000, 999_999)) * 10 + i
        eye_a = np.asarray(eye) + rng.uniform(-0.05, 0.05, size=3)
        room.require_inside(eye_a, f"camera SN{serial}")
        target_a = np.asarray(target) + rng.uniform(-0.15, 0.15, size=3)
        units.append(
            ZedUnit(
                index=i,
                serial=serial,
                node_id=node,
                factory=_factory(serial, rng),
                left_pose=Pose.look_at(eye_a, target_a),
            )
        )
    return tuple(units)
