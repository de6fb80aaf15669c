"""The calibration report's data and verdict: the numbers and a pass/fail a clinical engineer can
act on. The page and its pictures are ``report_page.py`` and ``report_plots.py``.

``quality_table`` and ``sensor_stats`` give the numbers for the calibration file's ``[quality]``
and ``[sensors.stats]`` tables; ``annotate`` puts them into a ``RigCalibration``; ``verdict``
says pass or fail, with reasons that say what to redo.

Residuals are *observed minus reprojected* pixel positions of the wand-sphere centres, in distorted
sensor pixels. Reprojection statistics are over the solver's inliers; the share it rejected is
judged separately.

Pass/fail limits (:class:`Thresholds`) and why:

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
  (300 by default, spread over the session, see ``calibration.extract``): enough to average
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

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from protocol.formats.rig_calibration import RigCalibration, SensorCalibration

log = logging.getLogger(__name__)

REPORT_FORMAT_VERSION = 1
PICTURES = {
    "coverage": "coverage.png",
    "residual_radius": "residual_vs_radius.png",
    "residual_hist": "residual_histograms.png",
    "rig": "rig_top_down.png",
    "wand": "wand_length.png",
}


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


def quality_table(data: ReportData, thresholds: Thresholds | None = None) -> dict[str, Any]:
    """The calibration file's ``[quality]``: overall reprojection (px, inliers), wand length (mm,
    sample SD as easyWand's MATLAB ``std``), wand score (%) and the verdict ("pass"/"fail")."""
    norm = data.residual_norm_px[data.obs_inlier]
    wl = data.wand_length_mm[np.isfinite(data.wand_length_mm)]
    mean_wl = float(np.mean(wl)) if wl.size else math.nan
    sd_wl = float(np.std(wl, ddof=1)) if wl.size > 1 else math.nan
    passed, _ = verdict(data, thresholds)
    return {
        **{f"reprojection_px_{k}": v for k, v in residual_stats(norm).items()},
        "observations": len(data.obs_inlier),
        "inliers": int(data.obs_inlier.sum()),
        "wand_sets": int(wl.size),
        "wand_length_mm_spec": float(data.wand_spec_length_mm),
        "wand_length_mm_mean": mean_wl,
        "wand_length_mm_sd": sd_wl,
        "wand_score": 100.0 * sd_wl / mean_wl if wl.size > 1 else math.nan,
        "verdict": "pass" if passed else "fail",
    }


def annotate(data: ReportData, thresholds: Thresholds | None = None) -> RigCalibration:
    """The calibration with ``quality`` and every sensor's ``stats`` filled in."""
    stats = sensor_stats(data, thresholds)
    sensors = tuple(replace(s, stats={**s.stats, **stats[s.name]}) for s in data.sensors)
    q = {**data.calibration.quality, **quality_table(data, thresholds)}
    return replace(data.calibration, sensors=sensors, quality=q)


def verdict(data: ReportData, thresholds: Thresholds | None = None) -> tuple[bool, list[str]]:
    """(passed, reasons): each reason says what is wrong, by how much, and what to do."""
    th = thresholds or data.thresholds
    reasons: list[str] = []
    q = _overall(data)
    redo = "then record the wand session again"
    if not data.obs_inlier.any():
        reasons.append(
            "The rig as a whole: no wand detection could be used, so nothing could be measured. "
            f"Check that the cameras were recording and the wand was in view; {redo}."
        )
    elif not q["mean"] <= th.mean_px:
        reasons.append(
            f"The rig as a whole: spheres appear on average {q['mean']:.2f} px away from where the "
            f"calibration puts them (reprojection error; limit {th.mean_px:.2f} px). Check that "
            f"no camera was knocked and that the lenses are clean; {redo}."
        )
    if data.obs_inlier.any() and not q["p95"] <= th.p95_px:
        reasons.append(
            f"The rig as a whole: 5 % of the sphere positions are off by more than {q['p95']:.2f} "
            f"px (limit {th.p95_px:.2f} px), a sign of mislabelled spheres, unsynchronised "
            f"cameras or a camera that moved during the recording. Check camera sync; {redo}."
        )
    wl = data.wand_length_mm[np.isfinite(data.wand_length_mm)]
    if wl.size < 2:
        reasons.append(
            "The wand was never measured in 3D: fewer than two sets were seen by two sensors. "
            f"Wave the wand where several cameras see it at once; {redo}."
        )
    else:
        mean, sd = float(np.mean(wl)), float(np.std(wl, ddof=1))
        score = 100 * sd / mean
        if not score <= th.wand_score_pct:
            reasons.append(
                f"The wand's measured length varies by {score:.2f} % (wand score; limit "
                f"{th.wand_score_pct:.2f} %): the cameras do not agree on where the spheres are. "
                f"Check camera sync and that the wand is rigid; {redo}."
            )
        bias = 100 * abs(mean - data.wand_spec_length_mm) / data.wand_spec_length_mm
        if not bias <= th.wand_bias_pct:
            reasons.append(
                f"The wand measures {mean:.1f} mm on average but should be "
                f"{data.wand_spec_length_mm:.1f} mm ({bias:.2f} % off; limit "
                f"{th.wand_bias_pct:.2f} %): the scale is wrong. Check that wand.toml describes "
                "the wand that was used."
            )
    reasons += _sensor_reasons(sensor_stats(data, th), th, redo)
    return (not reasons, reasons)


def _sensor_reasons(stats: dict[str, dict[str, float]], th: Thresholds, redo: str) -> list[str]:
    """One reason per failed check, naming every sensor that failed it (not one per sensor and
    check: when the whole rig is off, eight near-identical lines hide the message)."""
    seen = {n: st for n, st in stats.items() if st["observations"] > 0}
    blind = [n for n in stats if n not in seen]
    out = []
    if blind:
        out.append(
            f"{_who(blind, len(stats))} never saw the wand. Check that "
            f"{_pl(blind, 'it was', 'they were')} recording and not covered, and wave the wand "
            f"in {_its(blind)} view; {redo}."
        )

    def failing(key: str, ok: Any) -> tuple[list[str], list[float]]:
        bad = [(n, st[key]) for n, st in seen.items() if not ok(st[key])]
        return [n for n, _ in bad], [v for _, v in bad]

    names, v = failing("inlier_fraction", lambda f: f >= th.min_inlier_fraction)
    if names:
        who = _who(names, len(stats))
        pct = [100 * (1 - f) for f in v]
        out.append(
            f"{who}: {_span(pct, '.0f')} % of the sphere detections were rejected as "
            f"inconsistent (limit {100 * (1 - th.min_inlier_fraction):.0f} %). Check "
            f"synchronisation and that nothing sphere-like (lights, orange objects) is in view."
        )
    names, v = failing("reprojection_px_mean", lambda m: m <= th.sensor_mean_px)
    if names:
        who = _who(names, len(stats))
        out.append(
            f"{who}: mean reprojection error {_span(v, '.2f')} px (limit "
            f"{th.sensor_mean_px:.2f} px). Check that {_pl(names, 'it is', 'they are')} firmly "
            f"mounted and {_its(names)} lens clean; {redo}."
        )
    names, v = failing("reprojection_px_p95", lambda p: p <= th.p95_px)
    if names:
        who = _who(names, len(stats))
        out.append(
            f"{who}: 5 % of the sphere positions are off by more than {_span(v, '.2f')} "
            f"px (limit {th.p95_px:.2f} px). Check synchronisation and mounting."
        )
    names, v = failing("inlier_frames", lambda n: n >= th.min_frames)
    if names:
        who = _who(names, len(stats))
        out.append(
            f"{who} saw the wand in only {_span(v, '.0f')} usable frames (need at least "
            f"{th.min_frames}). Wave the wand longer where "
            f"{_pl(names, 'this camera', 'these cameras')} can see it."
        )
    names, v = failing("coverage_cells", lambda c: c >= th.min_coverage_cells)
    if names:
        who = _who(names, len(stats))
        out.append(
            f"{who}: the wand reached only {_span(v, '.0f')} of the "
            f"{th.coverage_grid**2} regions of {_pl(names, 'its image', 'their images')} (need "
            f"{th.min_coverage_cells}). Move the wand through the edges and corners of "
            f"{_its(names)} view (see the coverage map)."
        )
    return out


def _who(names: list[str], total: int) -> str:
    if len(names) == 1:
        return f"Camera {names[0]}"
    if len(names) == total:
        return f"All {total} sensors"
    return f"Cameras {', '.join(names[:-1])} and {names[-1]}"


def _pl(names: list[str], one: str, many: str) -> str:
    return one if len(names) == 1 else many


def _its(names: list[str]) -> str:
    return _pl(names, "its", "their")


def _span(values: list[float], fmt: str) -> str:
    lo, hi = min(values), max(values)
    a, b = format(lo, fmt), format(hi, fmt)
    return a if a == b else f"{a} to {b}"


def _overall(data: ReportData) -> dict[str, float]:
    return residual_stats(data.residual_norm_px[data.obs_inlier])
