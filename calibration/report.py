"""The calibration report: numbers, pictures and a pass/fail verdict a clinical engineer can act on.

``write_report(data, out_dir)`` writes ``report.html`` (self-contained: tables, the verdict at the
top, pictures embedded) and the pictures as PNGs next to it. ``quality_table`` and
``sensor_stats`` give the numbers for the calibration file's ``[quality]`` and
``[sensors.stats]`` tables; ``annotate`` puts them into a ``RigCalibration``.

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

import base64
import html
import io
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from protocol.rig_calibration import RigCalibration, SensorCalibration

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


# -- the report ---------------------------------------------------------------------------------
def write_report(
    data: ReportData, out_dir: Path | str, thresholds: Thresholds | None = None
) -> Path:
    """Write ``report.html`` and the PNG pictures into ``out_dir``; return the HTML's path."""
    th = thresholds or data.thresholds
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pngs = {
        "coverage": _plot_coverage(data, th),
        "residual_radius": _plot_residual_radius(data),
        "residual_hist": _plot_histograms(data, th),
        "rig": _plot_rig(data),
        "wand": _plot_wand(data, th),
    }
    for key, png in pngs.items():
        (out / PICTURES[key]).write_bytes(png)
    page = out / "report.html"
    page.write_text(_html(data, th, pngs))
    log.info("calibration report written to %s", page)
    return page


_CAPTIONS = {
    "coverage": (
        "Where each sensor saw the wand: darker cells hold more sphere detections. The grid is "
        "the {g}x{g} coverage check; a cross marks a cell with fewer than {p} detections. Red dots "
        "are detections the solver rejected."
    ),
    "residual_radius": (
        "Reprojection error against distance from the image centre. Top: size of the error, with "
        "its median per distance band. Bottom: the part pointing outward from the centre; a "
        "median that drifts away from zero at large distances shows an uncorrected lens or "
        "sphere-eccentricity bias."
    ),
    "residual_hist": (
        "Distribution of each sensor's reprojection error; solid line: mean, dashed: 95th "
        "percentile, red: the limits."
    ),
    "rig": (
        "The rig seen from above (left) and from the side (right), in metres in the world frame: "
        "camera centres with their viewing directions, labelled with serial numbers, and the path "
        "of the wand's middle sphere (colour: time) with the wand itself at regular intervals."
    ),
    "wand": (
        "Measured wand length minus its specified length, per set over the recording, with a "
        "running median and the +/- 1 SD band. A trend or jump means something changed during "
        "the recording (a camera moved, sync drifted)."
    ),
}

_CSS = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1200px;color:#222}
.banner{padding:1em 1.5em;border-radius:8px;margin-bottom:1.5em}
.pass{background:#e3f5e1;border:2px solid #2e7d32}.fail{background:#fdeaea;border:2px solid #c62828}
.banner h1{margin:0 0 .4em 0;font-size:1.6em}
table{border-collapse:collapse;margin:.5em 0 1.5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}th{background:#f3f3f3}
td:first-child,th:first-child{text-align:left}.bad{color:#c62828;font-weight:bold}
figure{margin:1em 0 2em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.9em;color:#444;max-width:900px}code{font-size:.9em}
"""


def _fmt(v: float, nd: int = 2) -> str:
    return "-" if not math.isfinite(v) else f"{v:.{nd}f}"


def _cell(text: str, bad: bool = False) -> str:
    return f'<td class="bad">{html.escape(text)}</td>' if bad else f"<td>{html.escape(text)}</td>"


def _table(header: list[str], rows: list[str]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    return f"<table><tr>{head}</tr>{''.join(f'<tr>{r}</tr>' for r in rows)}</table>"


def _html(data: ReportData, th: Thresholds, pngs: dict[str, bytes]) -> str:
    passed, reasons = verdict(data, th)
    q = quality_table(data, th)
    stats = sensor_stats(data, th)
    cal = data.calibration
    e = html.escape
    if passed:
        banner = (
            '<div class="banner pass"><h1>PASSED: the camera calibration is good enough to use.'
            "</h1><p>All cameras agree on where the wand was to within the limits below; 3D "
            "reconstructions made with this calibration will line up across cameras.</p></div>"
        )
    else:
        items = "".join(f"<li>{e(r)}</li>" for r in reasons)
        banner = (
            '<div class="banner fail"><h1>FAILED: do not use this calibration.</h1><p>The '
            "cameras' positions could not be measured precisely enough, so 3D reconstructions "
            "would not line up. What to fix:</p>"
            f"<ul>{items}</ul></div>"
        )
    wl_ok = not (q["wand_score"] > th.wand_score_pct)
    overall = _table(
        ["Quantity", "Value", "Limit"],
        [
            "<td>Mean reprojection error (px)</td>"
            + _cell(_fmt(q["reprojection_px_mean"]), not q["reprojection_px_mean"] <= th.mean_px)
            + f"<td>&le; {th.mean_px:g}</td>",
            f"<td>Median / RMS reprojection error (px)</td><td>{_fmt(q['reprojection_px_median'])}"
            f" / {_fmt(q['reprojection_px_rms'])}</td><td></td>",
            "<td>95th percentile reprojection error (px)</td>"
            + _cell(_fmt(q["reprojection_px_p95"]), not q["reprojection_px_p95"] <= th.p95_px)
            + f"<td>&le; {th.p95_px:g}</td>",
            f"<td>Observations kept / total</td><td>{q['inliers']} / {q['observations']}</td>"
            "<td></td>",
            f"<td>Wand length: spec / mean / SD (mm)</td><td>{q['wand_length_mm_spec']:.1f} / "
            f"{_fmt(q['wand_length_mm_mean'])} / {_fmt(q['wand_length_mm_sd'])}</td><td></td>",
            "<td>Wand score (100 SD / mean, %)</td>"
            + _cell(_fmt(q["wand_score"], 3), not wl_ok)
            + f"<td>&le; {th.wand_score_pct:g}</td>",
            f"<td>Sets with a measured wand</td><td>{q['wand_sets']}</td><td></td>",
        ],
    )
    rows = []
    for s in data.sensors:
        st = stats[s.name]
        w, h = data.image_size[s.name]
        _, _, why = data.frames.get(s.name, (0, 0, {}))
        why_txt = ", ".join(f"{k}: {v}" for k, v in sorted(why.items()))
        rows.append(
            f"<td>{e(s.name)}</td><td>{w}x{h}</td>"
            f"<td>{st['frames_used']}</td><td>{st['frames_rejected']}</td>"
            + _cell(str(st["inlier_frames"]), st["inlier_frames"] < th.min_frames)
            + f"<td>{st['inliers']} / {st['observations']}</td>"
            + _cell(
                _fmt(st["reprojection_px_mean"]),
                not st["reprojection_px_mean"] <= th.sensor_mean_px,
            )
            + f"<td>{_fmt(st['reprojection_px_median'])}</td>"
            + f"<td>{_fmt(st['reprojection_px_rms'])}</td>"
            + _cell(_fmt(st["reprojection_px_p95"]), not st["reprojection_px_p95"] <= th.p95_px)
            + _cell(
                f"{st['coverage_cells']} / {th.coverage_grid**2}",
                st["coverage_cells"] < th.min_coverage_cells,
            )
            + f"<td>{e(why_txt) or '-'}</td>"
        )
    per_sensor = _table(
        [
            "Sensor",
            "Image",
            "Frames used",
            "Frames rejected",
            "Usable frames",
            "Kept / seen",
            "Mean px",
            "Median px",
            "RMS px",
            "p95 px",
            "Coverage cells",
            "Rejection reasons",
        ],
        rows,
    )
    geo = []
    for s in data.sensors:
        i, c = s.intrinsics, s.pose.centre_m
        d = s.pose.R[2]  # optical axis in world coordinates
        geo.append(
            f"<td>{e(s.name)}</td><td>{i.fx_px:.2f}</td><td>{i.fy_px:.2f}</td>"
            f"<td>{i.cx_px:.2f}</td><td>{i.cy_px:.2f}</td>"
            f"<td>{' '.join(f'{v:.5g}' for v in i.dist)}</td>"
            f"<td>{c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}</td>"
            f"<td>{d[0]:.3f}, {d[1]:.3f}, {d[2]:.3f}</td>"
        )
    geometry = _table(
        [
            "Sensor",
            "fx px",
            "fy px",
            "cx px",
            "cy px",
            "k1 k2 p1 p2 k3",
            "Centre x, y, z (m)",
            "Looks along x, y, z",
        ],
        geo,
    )
    limits = _table(
        ["Limit", "Value"],
        [
            f"<td>Mean reprojection error, rig / each sensor</td><td>{th.mean_px:g} / "
            f"{th.sensor_mean_px:g} px</td>",
            f"<td>95th percentile reprojection error</td><td>{th.p95_px:g} px</td>",
            f"<td>Wand score</td><td>{th.wand_score_pct:g} %</td>",
            f"<td>Wand length off its spec</td><td>{th.wand_bias_pct:g} %</td>",
            f"<td>Usable frames per sensor</td><td>&ge; {th.min_frames}</td>",
            f"<td>Detections kept per sensor</td><td>&ge; {100 * th.min_inlier_fraction:g} %</td>",
            f"<td>Image regions reached per sensor</td><td>&ge; {th.min_coverage_cells} of "
            f"{th.coverage_grid}x{th.coverage_grid} (&ge; {th.min_points_per_cell} detections each)"
            "</td>",
        ],
    )
    figs = []
    for key, png in pngs.items():
        cap = _CAPTIONS[key].format(g=th.coverage_grid, p=th.min_points_per_cell)
        b64 = base64.b64encode(png).decode("ascii")
        figs.append(
            f'<figure><img alt="{key}" src="data:image/png;base64,{b64}">'
            f'<figcaption>{e(cap)} (<a href="{PICTURES[key]}">{PICTURES[key]}</a>)</figcaption>'
            "</figure>"
        )
    meta = {**cal.metadata}
    frame = (
        "z = 0 on the floor, z up"
        if cal.world_frame == "floor"
        else "the world is the named sensor's camera frame"
    )
    about = (
        f"<p>Resolution {e(cal.resolution.value)}; world frame <code>{e(cal.world_frame)}</code>"
        f" (metres; {frame}). Cameras use OpenCV axes (x right, y down, z forward); poses are "
        "world-to-camera, <code>x_cam = R x_world + t</code>. Pixel errors are observed minus "
        "reprojected sphere centres in sensor pixels, over the detections the solver kept.</p>"
        + (f"<p>{e(', '.join(f'{k}: {v}' for k, v in meta.items()))}</p>" if meta else "")
        + f"<p>Report format {REPORT_FORMAT_VERSION}.</p>"
    )
    return (
        f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{e(data.title)}</title>'
        f"<style>{_CSS}</style></head><body>{banner}<h2>{e(data.title)}</h2>"
        f"<h3>Overall</h3>{overall}<h3>Per sensor</h3>{per_sensor}"
        f"<h3>Pictures</h3>{''.join(figs)}<h3>Calibrated cameras</h3>{geometry}"
        f"<h3>Pass/fail limits</h3>{limits}<h3>Conventions</h3>{about}</body></html>\n"
    )


# -- pictures -----------------------------------------------------------------------------------
def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def _figure(w_in: float, h_in: float) -> Any:
    # the object API with an Agg canvas: no pyplot, no global backend switch in a library
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w_in, h_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _grid_layout(data: ReportData) -> tuple[int, int, list[tuple[int, int, SensorCalibration]]]:
    """Cameras as columns, left sensor above right, when the rig is made of stereo pairs."""
    serials = data.calibration.camera_serials
    pairs = all(
        {s.side for s in data.sensors if s.camera_serial == c} == {"left", "right"} for c in serials
    )
    if pairs and len(data.sensors) == 2 * len(serials):
        pos = [
            (0 if s.side == "left" else 1, serials.index(s.camera_serial), s) for s in data.sensors
        ]
        return 2, len(serials), pos
    ncols = min(4, len(data.sensors))
    nrows = -(-len(data.sensors) // ncols)
    return nrows, ncols, [(k // ncols, k % ncols, s) for k, s in enumerate(data.sensors)]


def _plot_coverage(data: ReportData, th: Thresholds) -> bytes:
    nrows, ncols, pos = _grid_layout(data)
    fig = _figure(4.2 * ncols, 3.0 * nrows + 0.4)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    g = th.coverage_grid
    for r, c, s in pos:
        ax = axes[r][c]
        w, h = data.image_size[s.name]
        inl, out = data.mask(s.name), data.mask(s.name, inliers=False) & ~data.obs_inlier
        px = data.obs_px[inl]
        hist, _, _ = np.histogram2d(px[:, 1], px[:, 0], bins=[30, 48], range=[[0, h], [0, w]])
        ax.imshow(
            np.log1p(hist),
            extent=(0, w, h, 0),
            cmap="Blues",
            vmin=0,
            interpolation="nearest",
            aspect="equal",
        )
        if out.any():
            ax.plot(*data.obs_px[out].T, ".", color="#d62728", ms=2, alpha=0.6)
        counts = coverage_counts(data, s.name, g)
        for k in range(1, g):
            ax.axhline(k * h / g, color="0.4", lw=0.6)
            ax.axvline(k * w / g, color="0.4", lw=0.6)
        for i in range(g):
            for j in range(g):
                if counts[i, j] < th.min_points_per_cell:
                    ax.plot((j + 0.5) * w / g, (i + 0.5) * h / g, "x", color="#c62828", ms=9, mew=2)
        hit = int((counts >= th.min_points_per_cell).sum())
        bad = hit < th.min_coverage_cells
        ax.set_title(
            f"{s.name}: {hit}/{g * g} cells", color="#c62828" if bad else "black", fontsize=10
        )
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.tick_params(labelsize=7)
    for r in range(nrows):
        for c in range(ncols):
            if not any(p[0] == r and p[1] == c for p in pos):
                axes[r][c].set_visible(False)
    fig.suptitle("Where the wand was seen (inlier detections per image area, pixels)")
    return _png(fig)


def _radii(data: ReportData) -> tuple[np.ndarray, np.ndarray]:
    """(M,) distance from the principal point in px, (M,) outward component of the residual."""
    cx = np.zeros(len(data.obs_sensor))
    cy = np.zeros(len(data.obs_sensor))
    by_name = {s.name: s for s in data.sensors}
    for k, name in enumerate(data.sensor_names):
        m = data.obs_sensor == k
        cx[m] = by_name[name].intrinsics.cx_px
        cy[m] = by_name[name].intrinsics.cy_px
    d = data.obs_px - np.column_stack([cx, cy])
    rad = np.hypot(d[:, 0], d[:, 1])
    unit = d / np.maximum(rad, 1e-9)[:, None]
    return rad, (data.obs_residual_px * unit).sum(axis=1)


def _binned_median(
    x: np.ndarray, y: np.ndarray, width: float = 50.0
) -> tuple[np.ndarray, np.ndarray]:
    if x.size == 0:
        return np.zeros(0), np.zeros(0)
    edges = np.arange(0.0, x.max() + width, width)
    idx = np.digitize(x, edges) - 1
    xs, ys = [], []
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() >= 5:
            xs.append(edges[b] + width / 2)
            ys.append(float(np.median(y[sel])))
    return np.asarray(xs), np.asarray(ys)


def _plot_residual_radius(data: ReportData) -> bytes:
    fig = _figure(10, 7)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    rad, outward = _radii(data)
    norm = data.residual_norm_px
    inl = data.obs_inlier
    sub = np.random.default_rng(0).permutation(np.flatnonzero(inl))[:20000]  # keep the PNG light
    ax1.plot(rad[sub], norm[sub], ".", ms=2, alpha=0.25, color="#1f77b4", label="inlier")
    if (~inl).any():
        ax1.plot(rad[~inl], norm[~inl], ".", ms=2, alpha=0.4, color="#d62728", label="rejected")
    ax1.plot(*_binned_median(rad[inl], norm[inl]), "-", color="black", lw=2, label="median")
    top = np.percentile(norm[inl], 99.5) * 1.2 if inl.any() else 1.0
    ax1.set_ylim(0, max(top, 0.5))
    ax1.set_ylabel("reprojection error (px)")
    ax1.legend(loc="upper left", fontsize=8)
    ax2.plot(rad[sub], outward[sub], ".", ms=2, alpha=0.25, color="#1f77b4")
    ax2.plot(*_binned_median(rad[inl], outward[inl]), "-", color="black", lw=2)
    ax2.axhline(0, color="0.5", lw=1)
    lim = np.percentile(np.abs(outward[inl]), 99.5) * 1.2 if inl.any() else 1.0
    ax2.set_ylim(-max(lim, 0.5), max(lim, 0.5))
    ax2.set_ylabel("outward part (px)")
    ax2.set_xlabel("distance from the principal point (px)")
    fig.suptitle("Reprojection error across the image (all sensors)")
    return _png(fig)


def _plot_histograms(data: ReportData, th: Thresholds) -> bytes:
    nrows, ncols, pos = _grid_layout(data)
    fig = _figure(3.6 * ncols, 2.6 * nrows + 0.4)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    norm = data.residual_norm_px
    inl_all = norm[data.obs_inlier]
    hi = max(2.0 * th.p95_px, float(np.percentile(inl_all, 99.5)) if inl_all.size else 0.0)
    for r, c, s in pos:
        ax = axes[r][c]
        v = norm[data.mask(s.name)]
        ax.hist(np.clip(v, 0, hi), bins=40, range=(0, hi), color="#1f77b4")
        if v.size:
            st = residual_stats(v)
            ax.axvline(st["mean"], color="black", lw=1.5)
            ax.axvline(st["p95"], color="black", lw=1.5, ls="--")
            ax.set_title(f"{s.name}: mean {st['mean']:.2f}, p95 {st['p95']:.2f}", fontsize=9)
        else:
            ax.set_title(f"{s.name}: no detections", fontsize=9, color="#c62828")
        ax.axvline(th.sensor_mean_px, color="#c62828", lw=1)
        ax.axvline(th.p95_px, color="#c62828", lw=1, ls="--")
        ax.set_xlabel("px", fontsize=8)
        ax.tick_params(labelsize=7)
    for rr in range(nrows):
        for cc in range(ncols):
            if not any(p[0] == rr and p[1] == cc for p in pos):
                axes[rr][cc].set_visible(False)
    fig.suptitle(
        "Reprojection error per sensor (inliers). Black: mean (solid) and 95th percentile "
        "(dashed); red: their limits"
    )
    return _png(fig)


def _plot_rig(data: ReportData) -> bytes:
    fig = _figure(13, 6)
    ax, side = fig.subplots(1, 2, width_ratios=[1.4, 1])
    traj = data.wand_trajectory_m
    ok = np.isfinite(traj).all(axis=(1, 2))
    mid = traj[ok, 1]
    for a, (i, j), name in ((ax, (0, 1), "y"), (side, (0, 2), "z")):
        if ok.any():
            a.scatter(mid[:, i], mid[:, j], c=np.flatnonzero(ok), s=2, cmap="viridis", alpha=0.6)
            step = max(1, int(ok.sum()) // 60)
            for t in traj[ok][::step]:
                a.plot(t[[0, 2], i], t[[0, 2], j], "-", color="0.55", lw=0.6)
        for s in data.sensors:
            c, d = s.pose.centre_m, s.pose.R[2]
            colour = "#1f77b4" if s.side == "left" else "#ff7f0e"
            a.plot(c[i], c[j], "o", color=colour, ms=6)
            a.annotate(
                "",
                xy=(c[i] + 1.0 * d[i], c[j] + 1.0 * d[j]),
                xytext=(c[i], c[j]),
                arrowprops={"arrowstyle": "->", "color": colour, "lw": 1.5},
            )
            if a is ax and (s.side == "left" or len({x.side for x in data.sensors}) == 1):
                a.annotate(
                    f"SN{s.camera_serial}",
                    (c[i], c[j]),
                    textcoords="offset points",
                    xytext=(6, 6),
                    fontsize=8,
                )
        a.set_xlabel("x (m)")
        a.set_ylabel(f"{name} (m)")
        a.set_aspect("equal", adjustable="datalim")
        a.grid(True, lw=0.3)
    ax.plot(0, 0, "+", color="black", ms=12)
    ax.set_title("Top view: cameras (blue left, orange right sensor) and the wand's path")
    side.set_title("Side view (x-z)")
    return _png(fig)


def _plot_wand(data: ReportData, th: Thresholds) -> bytes:
    fig = _figure(11, 4)
    ax, hx = fig.subplots(1, 2, width_ratios=[3, 1])
    err = data.wand_length_mm - data.wand_spec_length_mm
    ok = np.isfinite(err)
    k = np.flatnonzero(ok)
    e = err[ok]
    if e.size:
        ax.plot(k, e, ".", ms=3, alpha=0.5, color="#1f77b4")
        win = max(5, e.size // 50)
        if e.size >= win:
            run = np.array(
                [np.median(e[max(0, n - win // 2) : n + win // 2 + 1]) for n in range(e.size)]
            )
            ax.plot(k, run, "-", color="black", lw=1.5, label=f"running median ({win} sets)")
        mean = float(np.mean(e))
        sd = float(np.std(e, ddof=1)) if e.size > 1 else 0.0
        ax.axhspan(mean - sd, mean + sd, color="0.85", zorder=0, label="mean +/- 1 SD")
        ax.axhline(0, color="0.4", lw=1)
        bias_mm = th.wand_bias_pct / 100 * data.wand_spec_length_mm
        for b, lab in ((-bias_mm, f"scale limit +/- {th.wand_bias_pct:g} %"), (bias_mm, None)):
            ax.axhline(b, color="#c62828", lw=1, ls="--", label=lab)
        ax.legend(loc="upper right", fontsize=8)
        hx.hist(e, bins=40, orientation="horizontal", color="#1f77b4")
        hx.set_ylim(ax.get_ylim())
        score = 100 * sd / (mean + data.wand_spec_length_mm)
        ax.set_title(
            f"Wand length error: mean {mean:+.2f} mm, SD {sd:.2f} mm, wand score {score:.3f} % "
            f"(limit {th.wand_score_pct:g} %)",
            fontsize=10,
        )
    else:
        ax.set_title("The wand was never triangulated", color="#c62828")
    ax.set_xlabel("set")
    ax.set_ylabel("measured - spec (mm)")
    hx.set_xlabel("sets")
    return _png(fig)
