"""The calibration report's verdict: pass or fail, with reasons a clinical engineer can act on
(what is wrong, by how much, what to redo), judged against ``Thresholds``
(``calibration.report.thresholds`` says why each limit has its value).

``quality_table`` gives the numbers for the calibration file's ``[quality]`` table, verdict
included; ``annotate`` puts them and every sensor's ``[sensors.stats]`` into a ``RigCalibration``.
The page that shows all this is ``calibration.report.page``, its pictures
``calibration.report.plots``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from calibration.report.stats import ReportData, residual_stats, sensor_stats
from calibration.report.thresholds import Thresholds
from protocol.formats.rig_calibration import RigCalibration


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

    for key, ok, say in _sensor_checks(th, redo):
        bad = [(n, st[key]) for n, st in seen.items() if not ok(st[key])]
        if bad:
            names = [n for n, _ in bad]
            out.append(say(_who(names, len(stats)), names, [v for _, v in bad]))
    return out


_Check = tuple[str, Callable[[float], bool], Callable[[str, list[str], list[float]], str]]


def _sensor_checks(th: Thresholds, redo: str) -> list[_Check]:
    """Each per-sensor check: the ``sensor_stats`` key, when its value passes, and what to say
    (given who failed, their names and their values)."""
    return [
        (
            "inlier_fraction",
            lambda f: f >= th.min_inlier_fraction,
            lambda who, names, v: (
                f"{who}: {_span([100 * (1 - f) for f in v], '.0f')} % of the sphere detections "
                f"were rejected as inconsistent (limit {100 * (1 - th.min_inlier_fraction):.0f} "
                "%). Check synchronisation and that nothing sphere-like (lights, orange objects) "
                "is in view."
            ),
        ),
        (
            "reprojection_px_mean",
            lambda m: m <= th.sensor_mean_px,
            lambda who, names, v: (
                f"{who}: mean reprojection error {_span(v, '.2f')} px (limit "
                f"{th.sensor_mean_px:.2f} px). Check that {_pl(names, 'it is', 'they are')} firmly "
                f"mounted and {_its(names)} lens clean; {redo}."
            ),
        ),
        (
            "reprojection_px_p95",
            lambda p: p <= th.p95_px,
            lambda who, names, v: (
                f"{who}: 5 % of the sphere positions are off by more than {_span(v, '.2f')} "
                f"px (limit {th.p95_px:.2f} px). Check synchronisation and mounting."
            ),
        ),
        (
            "inlier_frames",
            lambda n: n >= th.min_frames,
            lambda who, names, v: (
                f"{who} saw the wand in only {_span(v, '.0f')} usable frames (need at least "
                f"{th.min_frames}). Wave the wand longer where "
                f"{_pl(names, 'this camera', 'these cameras')} can see it."
            ),
        ),
        (
            "coverage_cells",
            lambda c: c >= th.min_coverage_cells,
            lambda who, names, v: (
                f"{who}: the wand reached only {_span(v, '.0f')} of the "
                f"{th.coverage_grid**2} regions of {_pl(names, 'its image', 'their images')} "
                f"(need {th.min_coverage_cells}). Move the wand through the edges and corners of "
                f"{_its(names)} view (see the coverage map)."
            ),
        ),
    ]


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
