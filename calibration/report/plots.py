"""The calibration report's pictures, each a PNG as bytes: where each sensor saw the wand
(coverage), residuals against the distance from the image centre, residual histograms, the rig
from above, and the wand's triangulated length over the session."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from calibration.report.stats import ReportData, coverage_counts, residual_stats
from calibration.report.thresholds import Thresholds
from protocol.formats.rig_calibration import SensorCalibration


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


def plot_coverage(data: ReportData, th: Thresholds) -> bytes:
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


def plot_residual_radius(data: ReportData) -> bytes:
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


def plot_histograms(data: ReportData, th: Thresholds) -> bytes:
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


def plot_rig(data: ReportData) -> bytes:
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


def plot_wand(data: ReportData, th: Thresholds) -> bytes:
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
