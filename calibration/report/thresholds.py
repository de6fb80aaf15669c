"""The calibration report's pass/fail limits, :class:`Thresholds`.

Each limit and why:

- **Mean reprojection error <= 0.5 px overall, <= 0.6 px per sensor.** easyWand and Argus call a
  residual under 1 px "very good"; the paper's rig reports means of 0.44 and 0.55 px; our
  simulator goal is 0.3 px. Half of easyWand's "very good" keeps a margin for the reconstruction;
  a single sensor may sit slightly above the rig's mean, up to the paper's worse figure.
- **95th percentile <= 1.5 px, overall and per sensor.** For pure Gaussian noise the magnitude is
  Rayleigh-distributed and its p95 is about 1.95x its mean (about 1 px at a 0.5 px mean), so 1.5 px
  fails heavy tails, not noise: mislabelled spheres, a sync error (5 ms at 1 m/s costs 1.85 px at
  2 m) or a camera that moved.
- **Wand score <= 1.0 %** (100 * SD / mean of the triangulated wand length, easyWand's measure),
  and the mean wand length within 0.5 % of the spec (a scale error, e.g. a wrong ``wand.toml``).
- **At least 100 frames per sensor** with an inlier observation, among the sets calibration reads
  (300 by default, spread over the session, see ``calibration.detect.extract``): enough to average
  detection noise and to see the wand in many places. On the simulator a camera that saw the wand
  in 80 of 300 sets of a 2-minute session was still placed within 0.35 mm.
- **At least 80 % of a sensor's observations kept** by the solver; more rejections point to
  detection or synchronisation trouble, whatever the survivors' residuals say.
- **Coverage: at least 9 of the 16 cells of a 4x4 image grid** each holding at least 5 inlier
  observations. The top row of a wall-mounted camera looking down at the table sees the upper wall
  and ceiling, out of reach of a wand, so about 12 cells are reachable; 9 means the observations
  reach into most of the usable image (a sensor seen only in half its image fails), so the edges,
  where lens and sphere-eccentricity errors grow, are checked too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass(frozen=True, kw_only=True)
class Thresholds:
    """Pass/fail limits; the module docstring says why each has its value."""

    mean_px: float = 0.5  # overall mean reprojection error
    sensor_mean_px: float = 0.6  # per-sensor mean reprojection error
    p95_px: float = 1.5  # 95th percentile, overall and per sensor
    wand_score_pct: float = 1.0  # 100 * SD / mean wand length
    wand_bias_pct: float = 0.5  # |mean - spec| / spec
    min_frames: int = 100  # frames with an inlier observation, per sensor
    min_inlier_fraction: float = 0.8  # of a sensor's observations
    coverage_grid: int = 4  # the image is cut into grid x grid cells
    min_coverage_cells: int = 9
    min_points_per_cell: int = 5

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"Thresholds.{f.name}={v!r} must be a positive number")
        if self.min_inlier_fraction > 1:
            raise ValueError(f"Thresholds.min_inlier_fraction={self.min_inlier_fraction} is > 1")
        if self.min_coverage_cells > self.coverage_grid**2:
            raise ValueError(
                f"Thresholds.min_coverage_cells={self.min_coverage_cells} exceeds the "
                f"{self.coverage_grid}x{self.coverage_grid} grid"
            )
