"""``sightline`` over a case: the CSV, the timeline plot and the paired renders at the worst
instants, for the viewer's own position and a counterfactual one."""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Camera
from protocol.formats.site import SiteBox
from reconstructor.data.views import EYE_NEAR_M
from reconstructor.errors import CaseReplayError
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.observed_case import CaseObserved
from reconstructor.replay.path import CameraPath
from reconstructor.replay.run import case_raster, render_view
from reconstructor.replay.sightline import Offset, in_view_fraction, visible_fraction
from reconstructor.replay.video import burn_text, timecode

log = logging.getLogger(__name__)
VISIBLE_ENOUGH = 0.5  # "at least half visible": the binary answer


@dataclass(frozen=True)
class SightRow:
    t_s: float
    model: str
    position: str  # "actual" or the offset's text
    eye_m: tuple[float, float, float]
    visible_fraction: float
    in_view_fraction: float
    observed_share: float = float("nan")  # of the target's pixels (replay/observed_case.py)
    rests_on_inferred: bool = False


def sightline(
    folder: Path, path: CameraPath, box: SiteBox, offset: Offset | None, out: Path,
    *, size_px: tuple[int, int] = (480, 300), worst: int = 2, progress=None,
    device: str = "cpu",
) -> list[SightRow]:  # fmt: skip
    models = CaseModels(folder)
    p0, p1 = path.span_s
    entries = [e for e in models.entries if p0 - 1e-6 <= e.t_s <= p1 + 1e-6]
    if not entries:
        c0, c1 = models.span_s
        raise CaseReplayError(
            f"the viewer {path.name!r} ({p0:.3f}-{p1:.3f} s) and the case ({c0:.3f}-{c1:.3f} s) "
            "share no timestamp"
        )
    models.require_span(entries[0].t_s, entries[-1].t_s)
    raster = case_raster(folder, EYE_NEAR_M, device)
    observed = CaseObserved(folder, case_raster(folder, device=device))
    out.mkdir(parents=True, exist_ok=True)
    rows: list[SightRow] = []
    with ModelSource(models, entries) as source:
        for k, e in enumerate(entries):
            g = source.get(e)
            for label, cam in _positions(path, e.t_s, size_px, offset):
                frac, det = visible_fraction(g, cam.pose.centre_m, box, raster)
                eye = tuple(float(v) for v in cam.pose.centre_m)
                share = observed.target_share(e, g, det, raster)
                rows.append(SightRow(e.t_s, e.name, label, eye, frac, in_view_fraction(cam, box),  # type: ignore[arg-type]
                                     share, observed.rests_on_inferred(share)))  # fmt: skip
            if progress is not None:
                progress(k + 1, len(entries))
        _write_csv(out / "sightline.csv", rows, box)
        _plot(out / "timeline.png", rows, box, path.name)
        _worst_renders(out, rows, path, box, source, models, raster, size_px, offset, worst)
    return rows


def _positions(
    path: CameraPath, t_s: float, size_px: tuple[int, int], offset: Offset | None
) -> list[tuple[str, Camera]]:
    """(label, camera) of the viewer at ``t_s``: its own position ("actual") and, given an
    offset, the counterfactual one."""
    shifts = [("actual", np.zeros(3))]
    if offset is not None:
        shifts.append((offset.text, offset.world_shift_m(path.pose(t_s))))
    return [(label, path.camera(t_s, size_px, shift)) for label, shift in shifts]


def _write_csv(path: Path, rows: list[SightRow], box: SiteBox) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "model", "position", "eye_x_m", "eye_y_m", "eye_z_m", "target",
                    "visible_fraction", "in_view_fraction", "observed_share",
                    "rests_on_inferred"])  # fmt: skip
        for r in rows:
            eye = [f"{v:.3f}" for v in r.eye_m]
            fractions = [f"{r.visible_fraction:.3f}", f"{r.in_view_fraction:.3f}",
                         f"{r.observed_share:.3f}", int(r.rests_on_inferred)]  # fmt: skip
            w.writerow([f"{r.t_s:.3f}", r.model, r.position, *eye, box.name, *fractions])


def _plot(path: Path, rows: list[SightRow], box: SiteBox, viewer: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.2), dpi=110)
    labels = list(dict.fromkeys(r.position for r in rows))
    for i, label in enumerate(labels):
        sel = [r for r in rows if r.position == label]
        t = np.array([r.t_s for r in sel])
        f = np.array([r.visible_fraction for r in sel])
        colour = f"C{i}"
        ax.plot(t, f, "o-", color=colour, label=f"{viewer} {label}", ms=3)
        dt = np.median(np.diff(t)) if len(t) > 1 else 0.5
        for tk, fk in zip(t, f, strict=True):
            if fk < VISIBLE_ENOUGH:  # occluded: less than half visible, shaded
                ax.axvspan(tk - dt / 2, tk + dt / 2, color=colour, alpha=0.15, lw=0)
    ax.axhline(VISIBLE_ENOUGH, color="grey", ls=":", lw=1)
    ax.set(xlabel="case time (s)", ylabel=f"{box.name} visible", ylim=(-0.03, 1.03))
    ax.set_title(f"line of sight to {box.name} (shaded: less than half visible)", fontsize=10)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _worst_renders(out, rows, path, box, source, models, raster, size_px, offset, worst):
    """Side by side, at the instants the actual position saw least: the viewer's view and the
    counterfactual's, with the target's outline drawn in."""
    actual = sorted((r for r in rows if r.position == "actual"), key=lambda r: r.visible_fraction)
    for r in actual[:worst]:
        e = models.entry_at(r.t_s)
        g = source.get(e)
        panels = []
        for label, cam in _positions(path, r.t_s, size_px, offset):
            rgb, _, _ = render_view(g, cam, raster)
            outline_box(rgb, cam, box)
            frac = next(x.visible_fraction for x in rows if x.t_s == r.t_s and x.position == label)
            panels.append(burn_text(rgb, [f"{timecode(r.t_s)} {path.name} {label}",
                                          f"{box.name} visible {frac:.2f}"]))  # fmt: skip
        name = out / f"worst_{r.t_s:09.3f}.png"
        cv2.imwrite(str(name), np.concatenate(panels, axis=1)[:, :, ::-1])


def outline_box(rgb: np.ndarray, cam, box: SiteBox) -> None:
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / 2
    pts = (c * np.asarray(box.size_m)) @ box.rotation.T + np.asarray(box.centre_m)
    px, z = cam.project(pts)
    if np.any(z <= 0.05):
        return
    for a in range(8):
        for b in range(a + 1, 8):
            if bin(a ^ b).count("1") == 1:  # corners differing in one axis share an edge
                p, q = tuple(int(v) for v in px[a]), tuple(int(v) for v in px[b])
                cv2.line(rgb, p, q, (255, 210, 0), 2, cv2.LINE_AA)
