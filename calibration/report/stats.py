"""What the calibration report measures: ``ReportData`` (everything the report shows, filled by
the solver's caller) and the numbers drawn from it: ``residual_stats``, ``coverage_counts``,
``sensor_stats`` (a sensor's ``[sensors.stats]`` table).

Residuals are *observed minus reprojected* pixel positions of the wand-sphere centres, in distorted
sensor pixels. Reprojection statistics are over the solver's inliers; the share it rejected is
judged separately (``calibration.report.verdict``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.report.thresholds import Thresholds
from protocol.formats.rig_calibration import RigCalibration, SensorCalibration


@dataclass(frozen=True, kw_only=True, eq=False)  # eq on arrays is ambiguous; compare by identity
class ReportData:
    """Everything the report shows, filled by the solver's caller.

    ``obs_*`` are per observation (one wand-sphere centre seen by one sensor in one set), M rows:

    - ``obs_sensor`` (M,) int: index into ``sensor_names``;
    - ``obs_px`` (M, 2): the observed (distorted) pixel;
    - ``obs_residual_px`` (M, 2): observed minus reprojected pixel;
    - ``obs_inlier`` (M,) bool: kept by the solver;
    - ``obs_set`` (M,) int, optional: the synchronised set's index; frames are counted from it
      (without it, "usable frames" are the ``frames used`` the caller reports).

    ``wand_length_mm`` (K,): the triangulated first-to-last sphere distance per set (NaN allowed).
    ``wand_trajectory_m`` (N, 3, 3): sphere centres per set in world metres (NaN where not
    triangulated). ``frames``: sensor name -> (frames used, frames rejected, {reason: count}).
    ``image_size``: sensor name -> (width, height); by default the calibration's.
    """

    calibration: RigCalibration
    sensor_names: tuple[str, ...]
    obs_sensor: np.ndarray
    obs_px: np.ndarray
    obs_residual_px: np.ndarray
    obs_inlier: np.ndarray
    wand_length_mm: np.ndarray
    wand_spec_length_mm: float
    frames: Mapping[str, tuple[int, int, Mapping[str, int]]] = field(default_factory=dict)
    wand_trajectory_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    image_size: Mapping[str, tuple[int, int]] = field(default_factory=dict)
    obs_set: np.ndarray | None = None
    thresholds: Thresholds = field(default_factory=Thresholds)
    title: str = "EgoSurg rig calibration"

    def __post_init__(self) -> None:
        def arr(name: str, dtype: Any, shape: tuple[int | None, ...]) -> np.ndarray:
            a = np.asarray(getattr(self, name), dtype=dtype)
            if a.ndim != len(shape) or any(
                s is not None and s != n for s, n in zip(shape, a.shape, strict=True)
            ):
                want = "x".join("M" if s is None else str(s) for s in shape)
                raise ValueError(f"ReportData.{name} has shape {a.shape}, expected ({want})")
            object.__setattr__(self, name, a)
            return a

        m = len(np.asarray(self.obs_sensor))
        arr("obs_sensor", np.int64, (m,))
        arr("obs_px", np.float64, (m, 2))
        arr("obs_residual_px", np.float64, (m, 2))
        arr("obs_inlier", bool, (m,))
        arr("wand_length_mm", np.float64, (None,))
        arr("wand_trajectory_m", np.float64, (None, 3, 3))
        if self.obs_set is not None:
            arr("obs_set", np.int64, (m,))
        object.__setattr__(self, "sensor_names", tuple(self.sensor_names))
        if m and (self.obs_sensor.min() < 0 or self.obs_sensor.max() >= len(self.sensor_names)):
            raise ValueError(
                f"ReportData.obs_sensor must index sensor_names (0..{len(self.sensor_names) - 1})"
            )
        known = {s.name for s in self.calibration.sensors}
        unknown = [n for n in self.sensor_names if n not in known]
        if unknown:
            raise ValueError(f"ReportData.sensor_names {unknown} are not in the calibration")
        if not self.wand_spec_length_mm > 0:
            raise ValueError(
                f"ReportData.wand_spec_length_mm={self.wand_spec_length_mm} must be > 0"
            )
        sizes = {
            s.name: (s.intrinsics.width_px, s.intrinsics.height_px)
            for s in self.calibration.sensors
        }
        object.__setattr__(self, "image_size", {**sizes, **dict(self.image_size)})

    # -- derived views ---------------------------------------------------------------------------
    @property
    def sensors(self) -> tuple[SensorCalibration, ...]:
        """Every calibrated sensor, in the calibration's order (some may have no observations)."""
        return self.calibration.sensors

    def mask(self, name: str, inliers: bool = True) -> np.ndarray:
        """(M,) bool: this sensor's observations (inliers only by default)."""
        if name not in self.sensor_names:
            return np.zeros(len(self.obs_sensor), bool)
        m = self.obs_sensor == self.sensor_names.index(name)
        return m & self.obs_inlier if inliers else m

    @property
    def residual_norm_px(self) -> np.ndarray:
        """(M,) residual magnitudes."""
        return np.hypot(self.obs_residual_px[:, 0], self.obs_residual_px[:, 1])


def residual_stats(r: np.ndarray) -> dict[str, float]:
    """Mean, RMS, median, p95 and max of residual magnitudes (NaN if there are none)."""
    r = np.asarray(r, dtype=np.float64)
    if r.size == 0:
        return {k: math.nan for k in ("mean", "rms", "median", "p95", "max")}
    return {
        "mean": float(np.mean(r)),
        "rms": float(np.sqrt(np.mean(r * r))),
        "median": float(np.median(r)),
        "p95": float(np.percentile(r, 95)),
        "max": float(np.max(r)),
    }


def coverage_counts(data: ReportData, name: str, grid: int | None = None) -> np.ndarray:
    """(grid, grid) inlier observations per image cell, [row, column], row 0 at the top."""
    g = grid or data.thresholds.coverage_grid
    w, h = data.image_size[name]
    px = data.obs_px[data.mask(name)]
    counts, _, _ = np.histogram2d(px[:, 1], px[:, 0], bins=[g, g], range=[[0, h], [0, w]])
    return counts.astype(np.int64)


def sensor_stats(
    data: ReportData, thresholds: Thresholds | None = None
) -> dict[str, dict[str, float]]:
    """Per-sensor numbers for ``[sensors.stats]``, keyed by sensor name."""
    th = thresholds or data.thresholds
    norm = data.residual_norm_px
    out = {}
    for s in data.sensors:
        every, inl = data.mask(s.name, inliers=False), data.mask(s.name)
        st = residual_stats(norm[inl])
        used, rejected, _ = data.frames.get(s.name, (0, 0, {}))
        if data.obs_set is not None:
            frames = len(np.unique(data.obs_set[inl]))
        else:
            frames = int(used)
        cells = int(
            (coverage_counts(data, s.name, th.coverage_grid) >= th.min_points_per_cell).sum()
        )
        out[s.name] = {
            **{f"reprojection_px_{k}": v for k, v in st.items()},
            "observations": int(every.sum()),
            "inliers": int(inl.sum()),
            "inlier_fraction": float(inl.sum() / every.sum()) if every.any() else math.nan,
            "inlier_frames": int(frames),
            "frames_used": int(used),
            "frames_rejected": int(rejected),
            "coverage_cells": cells,
        }
    return out
