"""What the solver works from: labelled wand-sphere centres per synchronised set and sensor.

The hand-off between the two halves of calibration, so it sits between them: built from a
recorded session by ``calibration.detect.extract`` (detection and labelling of every frame), or
synthesised from the simulator's truth in tests, and read by ``calibration.solve``. Everything a
solver needs travels in one object, so the solver never touches images or files.

Conventions: pixel coordinates are *distorted* sensor pixels (as in the image) of the projection
of each sphere's centre, already corrected for the eccentricity bias of the sphere's imaged
ellipse; sphere order follows the wand spec (first, middle, last along the rod).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.camera import Intrinsics
from protocol.formats.wand import WandSpec
from protocol.formats.zed_conf import StereoCalibration

SIDES = ("left", "right")


@dataclass(frozen=True, order=True)
class SensorKey:
    camera_serial: int
    side: str

    @property
    def name(self) -> str:
        return f"SN{self.camera_serial}-{self.side}"


@dataclass
class WandObservations:
    """``points_px[k, s, j]`` is sphere j seen by sensor s in set k, NaN where not seen.

    ``sensors`` lists the sensors in column order, left and right of each camera, cameras in
    ``camera_serials`` order. ``stereo`` holds each camera's factory intrinsics and left-to-right
    transform, which the solver keeps fixed: it estimates one pose per camera (rig), not per sensor.
    """

    wand: WandSpec
    camera_serials: tuple[int, ...]
    stereo: dict[int, StereoCalibration]
    set_unix_ns: np.ndarray  # (N,) int64
    points_px: np.ndarray  # (N, S, 3, 2) float64
    rejected: dict[SensorKey, dict[str, int]] = field(default_factory=dict)
    frames_seen: dict[SensorKey, int] = field(default_factory=dict)
    image_size: dict[SensorKey, tuple[int, int]] = field(default_factory=dict)
    frames_decoded: int = 0  # images decoded to find the wand (for timing reports)

    def __post_init__(self) -> None:
        n, s = len(self.set_unix_ns), len(self.sensors)
        if self.points_px.shape != (n, s, 3, 2):
            raise ValueError(f"points_px has shape {self.points_px.shape}, expected {(n, s, 3, 2)}")

    @property
    def sensors(self) -> tuple[SensorKey, ...]:
        return tuple(SensorKey(c, side) for c in self.camera_serials for side in SIDES)

    def intrinsics(self, key: SensorKey) -> Intrinsics:
        st = self.stereo[key.camera_serial]
        return st.left if key.side == "left" else st.right

    def seen(self) -> np.ndarray:
        """(N, S) bool: sensor s saw all three spheres of set k."""
        return np.isfinite(self.points_px).all(axis=(2, 3))

    def frames_used(self) -> dict[SensorKey, int]:
        seen = self.seen()
        return {key: int(seen[:, i].sum()) for i, key in enumerate(self.sensors)}
