"""``sightline`` over a case: the CSV, the timeline plot and the paired renders at the worst
instants, for the viewer's own position and a counterfactual one.

A timestamp inside one of the viewer's gaps (an estimated role seen by no camera there, or
between two of the tracks it joins) gets no answer: no row, no plan, a warning with the count,
and on the timeline a grey band ("not followed") that the line does not cross. Another role
inside one of its gaps is not drawn on the plans and blocks no one's line.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Camera
from protocol.formats.site import SiteBox, surface_points
from protocol.formats.trajectory import TIME_RESOLUTION_S
from protocol.sealing import Identity
from reconstructor.data.views import EYE_NEAR_M
from reconstructor.errors import CaseReplayError
from reconstructor.replay.clock import CaseClock, add_time_of_day_axis, pick_zone
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.observed_case import CaseObserved
from reconstructor.replay.path import CameraPath
from reconstructor.replay.plan import TURNED_AWAY, describe_blockers, who_blocks
from reconstructor.replay.run import case_raster
from reconstructor.replay.session_check import write_made_for
from reconstructor.replay.sightline import Offset, in_view_fraction, visible_fraction
from reconstructor.replay.sightline_pictures import (
    VISIBLE_ENOUGH,  # "at least half visible": the binary answer
    SightScene,
    answer_plan,
    worst_picture,
)

log = logging.getLogger(__name__)
SAMPLES_PER_FACE = 12  # visible_fraction's grid (its default), to name who blocks each point


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
    # (role or plan.OTHER, share of the target's points) on the line, largest first; () none
    blockers: tuple[tuple[str, float], ...] = ()


def sightline(
    folder: Path, path: CameraPath, box: SiteBox, offset: Offset | None, out: Path,
    *, size_px: tuple[int, int] = (480, 300), worst: int = 2, progress=None,
    device: str = "cpu", identity: Identity | None = None,
    others: tuple[CameraPath, ...] = (), site_boxes: tuple[SiteBox, ...] = (),
    timezone: str | None = None,
) -> list[SightRow]:  # fmt: skip
    """Rows for each timestamp and position; ``others`` (the roles file's people) say who
    blocks the line and stand on the plans with ``site_boxes`` (sightline_pictures.py)."""
    models = CaseModels(folder, identity)  # a sealed session's case opens with it
    scene = SightScene.for_case(folder, site_boxes, others, CaseClock.for_case(folder,
                                pick_zone(timezone)))  # fmt: skip
    p0, p1 = path.span_s
    tol = TIME_RESOLUTION_S
    entries = [e for e in models.entries if p0 - tol <= e.t_s <= p1 + tol]
    if not entries:
        c0, c1 = models.span_s
        raise CaseReplayError(
            f"the viewer {path.name!r} ({p0:.3f}-{p1:.3f} s) and the case ({c0:.3f}-{c1:.3f} s) "
            "share no timestamp"
        )
    models.require_span(entries[0].t_s, entries[-1].t_s)
    entries = _followed(entries, path)
    raster = case_raster(folder, EYE_NEAR_M, device)
    observed = CaseObserved(folder, case_raster(folder, device=device))
    out.mkdir(parents=True, exist_ok=True)
    rows: list[SightRow] = []
    with ModelSource(models, entries) as source:
        for k, e in enumerate(entries):
            g = source.get(e)
            people = scene.people_at(e.t_s, path.name)
            for label, cam in _positions(path, e.t_s, size_px, offset):
                frac, det = visible_fraction(g, cam.pose.centre_m, box, raster)
                eye = tuple(float(v) for v in cam.pose.centre_m)
                share = observed.target_share(e, g, det, raster)
                rows.append(SightRow(e.t_s, e.name, label, eye, frac, in_view_fraction(cam, box),  # type: ignore[arg-type]
                                     share, observed.rests_on_inferred(share),
                                     _blockers(cam.pose.centre_m, box, det, people)))  # fmt: skip
            at_t = [r for r in rows if r.t_s == e.t_s]
            plan = answer_plan(at_t, path.name, box, scene, path=path)
            _write_png(out / f"plan_{e.t_s:09.3f}.png", plan)
            if progress is not None:
                progress(k + 1, len(entries))
        _write_csv(out / "sightline.csv", rows, box)
        _plot(out / "timeline.png", rows, box, path.name, scene.clock, path.gaps_s)
        _worst_renders(out, rows, path, box, source, models, raster, size_px, worst, scene)
    # egosurg report checks the folder's session
    write_made_for(out, folder, "sightline", f"{path.name} sees {box.name}")
    return rows


def _followed(entries: list, path: CameraPath) -> list:
    """The timestamps outside the viewer's gaps: inside one, nobody knows where the eye was."""
    kept = [e for e in entries if path.gap_at(e.t_s) is None]
    if len(kept) < len(entries):
        spans = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in path.gaps_s)
        log.warning(
            "sightline: %d of %d timestamps fall in %s's gaps (%s: seen by no camera, or between "
            "two tracks) and get no answer", len(entries) - len(kept), len(entries), path.name,
            spans,
        )  # fmt: skip
    if not kept:
        raise CaseReplayError(
            f"every timestamp the viewer {path.name!r} spans falls in one of its gaps (seen by "
            "no camera, or between two tracks): no eye to answer from; name a track that covers "
            "the case's timestamps"
        )
    return kept


def obstruction_words(rows: list[SightRow], position: str) -> str:
    """``no obstruction at 5 of 7 timestamps; blocked by circulator at 2``: who stood on the line
    at how many of the position's timestamps."""
    sel = [r for r in rows if r.position == position]
    clear = sum(not r.blockers for r in sel)
    counts: dict[str, int] = {}
    for r in sel:
        for role, _ in r.blockers:
            counts[role] = counts.get(role, 0) + 1
    words = f"no obstruction at {clear} of {len(sel)} timestamps"
    if counts:
        ranked = sorted(counts.items(), key=lambda kv: -kv[1])
        words += "; blocked by " + ", ".join(f"{role} at {n}" for role, n in ranked)
    return words


def _blockers(eye_m, box: SiteBox, det: dict, people) -> tuple[tuple[str, float], ...]:
    """Who stands on the line to each blocked sample point of the box (plan.who_blocks)."""
    if "visible" not in det:  # no counted face of the box faces the eye: seen from behind
        return ((TURNED_AWAY, 1.0),)
    points = surface_points(box, np.asarray(eye_m, float), SAMPLES_PER_FACE)
    if len(points) != len(det["visible"]):
        raise CaseReplayError("sightline: the blocked points and their samples disagree")
    return tuple(who_blocks(eye_m, points, ~det["visible"], people).items())


def _write_png(path: Path, rgb: np.ndarray) -> None:
    cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1]))


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
                    "rests_on_inferred", "blocked_by"])  # fmt: skip
        for r in rows:
            eye = [f"{v:.3f}" for v in r.eye_m]
            fractions = [f"{r.visible_fraction:.3f}", f"{r.in_view_fraction:.3f}",
                         f"{r.observed_share:.3f}", int(r.rests_on_inferred)]  # fmt: skip
            w.writerow([f"{r.t_s:.3f}", r.model, r.position, *eye, box.name, *fractions,
                        describe_blockers(dict(r.blockers), box.name)])  # fmt: skip


def _plot(
    path: Path, rows: list[SightRow], box: SiteBox, viewer: str, clock: CaseClock | None = None,
    gaps_s: tuple[tuple[float, float], ...] = (),
) -> None:  # fmt: skip
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
        # the line never crosses a gap: between two answers on either side of one, a break
        cut = [k for k in range(1, len(t)) if any(t[k - 1] < b and a < t[k] for a, b in gaps_s)]
        ax.plot(np.insert(t, cut, np.nan), np.insert(f, cut, np.nan), "o-", color=colour,
                label=f"{viewer} {label}", ms=3)  # fmt: skip
        dt = np.median(np.diff(t)) if len(t) > 1 else 0.5
        for tk, fk in zip(t, f, strict=True):
            if fk < VISIBLE_ENOUGH:  # occluded: less than half visible, shaded
                ax.axvspan(tk - dt / 2, tk + dt / 2, color=colour, alpha=0.15, lw=0)
    t_all = [r.t_s for r in rows]
    shown = [(max(a, min(t_all)), min(b, max(t_all))) for a, b in gaps_s]  # within the answers
    for k, (a, b) in enumerate((a, b) for a, b in shown if a < b):
        ax.axvspan(a, b, color="grey", alpha=0.3, lw=0, label="not followed" if k == 0 else None)
    ax.axhline(VISIBLE_ENOUGH, color="grey", ls=":", lw=1)
    ax.set(xlabel="case time (s)", ylabel=f"{box.name} visible", ylim=(-0.03, 1.03))
    ax.set_title(f"line of sight to {box.name} (shaded: less than half visible)", fontsize=10)
    ax.legend(fontsize=8, loc="lower left")
    if clock is not None:
        add_time_of_day_axis(ax, clock)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _worst_renders(out, rows, path, box, source, models, raster, size_px, worst, scene):
    """At the instants the actual position saw least: the views from each position, aimed at
    the target, beside the plan (sightline_pictures.py)."""
    actual = sorted((r for r in rows if r.position == "actual"), key=lambda r: r.visible_fraction)
    for r in actual[:worst]:
        g = source.get(models.entry_at(r.t_s))
        at_t = [x for x in rows if x.t_s == r.t_s]
        picture = worst_picture(at_t, path, box, g, raster, size_px, scene)
        _write_png(out / f"worst_{r.t_s:09.3f}.png", picture)
