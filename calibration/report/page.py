"""The calibration report as a page: ``write_report(data, out_dir)`` writes ``report.html``
(self-contained: the verdict at the top, tables, pictures embedded) and the pictures as PNGs next
to it. The numbers come from ``calibration.report.stats``, the verdict from
``calibration.report.verdict`` and the pictures from ``calibration.report.plots``: the page only
lays them out.
"""

from __future__ import annotations

import base64
import html
import logging
import math
from pathlib import Path

from calibration.report.plots import (
    plot_coverage,
    plot_histograms,
    plot_residual_radius,
    plot_rig,
    plot_wand,
)
from calibration.report.stats import ReportData, sensor_stats
from calibration.report.thresholds import Thresholds
from calibration.report.verdict import quality_table, verdict

log = logging.getLogger(__name__)

REPORT_FORMAT_VERSION = 1
PICTURES = {
    "coverage": "coverage.png",
    "residual_radius": "residual_vs_radius.png",
    "residual_hist": "residual_histograms.png",
    "rig": "rig_top_down.png",
    "wand": "wand_length.png",
}


# -- the page ---------------------------------------------------------------------------------
def write_report(
    data: ReportData, out_dir: Path | str, thresholds: Thresholds | None = None
) -> Path:
    """Write ``report.html`` and the PNG pictures into ``out_dir``; return the HTML's path."""
    th = thresholds or data.thresholds
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pngs = {
        "coverage": plot_coverage(data, th),
        "residual_radius": plot_residual_radius(data),
        "residual_hist": plot_histograms(data, th),
        "rig": plot_rig(data),
        "wand": plot_wand(data, th),
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
    e = html.escape
    return (
        f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{e(data.title)}</title>'
        f"<style>{_CSS}</style></head><body>{_banner(data, th)}<h2>{e(data.title)}</h2>"
        f"<h3>Overall</h3>{_overall(data, th)}<h3>Per sensor</h3>{_per_sensor(data, th)}"
        f"<h3>Pictures</h3>{_figures(pngs, th)}<h3>Calibrated cameras</h3>{_geometry(data)}"
        f"<h3>Pass/fail limits</h3>{_limits(th)}<h3>Conventions</h3>{_about(data)}</body></html>\n"
    )


def _banner(data: ReportData, th: Thresholds) -> str:
    """The verdict, first thing on the page: pass, or fail with what to fix."""
    passed, reasons = verdict(data, th)
    if passed:
        return (
            '<div class="banner pass"><h1>PASSED: the camera calibration is good enough to use.'
            "</h1><p>All cameras agree on where the wand was to within the limits below; 3D "
            "reconstructions made with this calibration will line up across cameras.</p></div>"
        )
    items = "".join(f"<li>{html.escape(r)}</li>" for r in reasons)
    return (
        '<div class="banner fail"><h1>FAILED: do not use this calibration.</h1><p>The '
        "cameras' positions could not be measured precisely enough, so 3D reconstructions "
        "would not line up. What to fix:</p>"
        f"<ul>{items}</ul></div>"
    )


def _overall(data: ReportData, th: Thresholds) -> str:
    q = quality_table(data, th)
    wl_ok = not (q["wand_score"] > th.wand_score_pct)
    return _table(
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


_SENSOR_HEADER = [
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
]


def _per_sensor(data: ReportData, th: Thresholds) -> str:
    stats = sensor_stats(data, th)
    e = html.escape
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
    return _table(_SENSOR_HEADER, rows)


_GEOMETRY_HEADER = [
    "Sensor",
    "fx px",
    "fy px",
    "cx px",
    "cy px",
    "k1 k2 p1 p2 k3 [k4 k5 k6]",
    "Centre x, y, z (m)",
    "Looks along x, y, z",
]


def _geometry(data: ReportData) -> str:
    geo = []
    for s in data.sensors:
        i, c = s.intrinsics, s.pose.centre_m
        d = s.pose.R[2]  # optical axis in world coordinates
        geo.append(
            f"<td>{html.escape(s.name)}</td><td>{i.fx_px:.2f}</td><td>{i.fy_px:.2f}</td>"
            f"<td>{i.cx_px:.2f}</td><td>{i.cy_px:.2f}</td>"
            f"<td>{' '.join(f'{v:.5g}' for v in i.dist)}</td>"
            f"<td>{c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}</td>"
            f"<td>{d[0]:.3f}, {d[1]:.3f}, {d[2]:.3f}</td>"
        )
    return _table(_GEOMETRY_HEADER, geo)


def _limits(th: Thresholds) -> str:
    return _table(
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


def _figures(pngs: dict[str, bytes], th: Thresholds) -> str:
    figs = []
    for key, png in pngs.items():
        cap = _CAPTIONS[key].format(g=th.coverage_grid, p=th.min_points_per_cell)
        b64 = base64.b64encode(png).decode("ascii")
        figs.append(
            f'<figure><img alt="{key}" src="data:image/png;base64,{b64}">'
            f"<figcaption>{html.escape(cap)} "
            f'(<a href="{PICTURES[key]}">{PICTURES[key]}</a>)</figcaption>'
            "</figure>"
        )
    return "".join(figs)


def _about(data: ReportData) -> str:
    cal = data.calibration
    e = html.escape
    meta = {**cal.metadata}
    frame = (
        "z = 0 on the floor, z up"
        if cal.world_frame == "floor"
        else "the world is the named sensor's camera frame"
    )
    return (
        f"<p>Resolution {e(cal.resolution.value)}; world frame <code>{e(cal.world_frame)}</code>"
        f" (metres; {frame}). Cameras use OpenCV axes (x right, y down, z forward); poses are "
        "world-to-camera, <code>x_cam = R x_world + t</code>. Pixel errors are observed minus "
        "reprojected sphere centres in sensor pixels, over the detections the solver kept.</p>"
        + (f"<p>{e(', '.join(f'{k}: {v}' for k, v in meta.items()))}</p>" if meta else "")
        + f"<p>Report format {REPORT_FORMAT_VERSION}.</p>"
    )
