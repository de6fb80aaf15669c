"""The report's timeline: one picture over the case's span, in case time with the time of day
beneath, holding the case's timestamps, the sterile events (contacts in colour by field, sterile
roles' entries in grey), each line-of-sight answer (the target's visible fraction, shaded where
less than half of it is visible) and the times the thumbnails show."""

from __future__ import annotations

import io

import numpy as np

from reconstructor.replay.clock import CaseClock
from reconstructor.report.reviews import SightlineReview, SterileReview

VISIBLE_ENOUGH = 0.5  # reconstructor/replay/sightline_run.py's "at least half visible"


def timeline_png(
    clock: CaseClock, span_s: tuple[float, float], done_s: list[float], missing_s: list[float],
    sterile: SterileReview | None, sightlines: list[SightlineReview], thumb_times_s: list[float],
) -> bytes:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = 2 + len(sightlines)
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.0 + 1.1 * rows), dpi=120, sharex=True,
                             gridspec_kw={"height_ratios": [0.5, 1.0] + [1.3] * len(sightlines)},
                             squeeze=False)  # fmt: skip
    ax_case, ax_field = axes[0, 0], axes[1, 0]
    spacing = float(np.median(np.diff(done_s))) if len(done_s) > 1 else 0.5
    ax_case.plot(done_s, [0.5] * len(done_s), "|", color="0.2", ms=12)
    if missing_s:
        ax_case.plot(missing_s, [0.5] * len(missing_s), "x", color="crimson", ms=7)
    ax_case.set_yticks([])
    what = "timestamps\n(x: pending, failed)" if missing_s else "timestamps"
    ax_case.set_ylabel(what, rotation=0, ha="right", va="center", fontsize=8)
    _field(ax_field, sterile, spacing)
    for ax, review in zip(axes[2:, 0], sightlines, strict=True):
        _sight(ax, review, spacing)
    for ax in axes[:, 0]:
        for t in thumb_times_s:
            ax.axvline(t, color="0.5", ls=":", lw=0.8)
    lo, hi = span_s
    pad = max(spacing / 2, 0.05)
    last = axes[-1, 0]
    last.set_xlim(lo - pad, hi + pad)
    ticks = last.get_xticks()
    ticks = [t for t in ticks if lo - pad <= t <= hi + pad]
    last.set_xticks(ticks)
    last.set_xticklabels([f"{t:g} s\n{clock.time_of_day(t)[:8]}" for t in ticks], fontsize=7)
    zone = clock.at(0.0).strftime("%Z (UTC%z)")
    last.set_xlabel(f"case time (s) and time of day, {zone}; dotted: the role views' times")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def _field(ax, sterile: SterileReview | None, spacing: float) -> None:
    ax.set_yticks([])
    ax.set_ylabel("sterile\nfield", rotation=0, ha="right", va="center")
    if sterile is None:
        ax.text(0.5, 0.5, "not run", transform=ax.transAxes, ha="center", va="center",
                color="0.4")  # fmt: skip
        return
    fields = list(dict.fromkeys(e.field for e in sterile.events)) or [""]
    for e in sterile.events:
        y = fields.index(e.field)
        span = (e.start_s - spacing / 2, e.end_s + spacing / 2)
        if e.contact:
            ax.barh(y, span[1] - span[0], left=span[0], height=0.6, color="crimson", alpha=0.7)
            ax.text(span[0], y, f" {e.number}: {e.role}", va="center", fontsize=7)
        else:
            ax.barh(y, span[1] - span[0], left=span[0], height=0.25, color="0.6")
    ax.set_yticks(range(len(fields)), fields, fontsize=7)
    ax.set_ylim(-0.6, len(fields) - 0.4)
    if not sterile.events:
        ax.text(0.5, 0.5, "no event", transform=ax.transAxes, ha="center", va="center")


def _sight(ax, review: SightlineReview, spacing: float) -> None:
    positions = list(dict.fromkeys(r.position for r in review.rows))
    for i, label in enumerate(positions):
        sel = [r for r in review.rows if r.position == label]
        t = np.array([r.t_s for r in sel])
        f = np.array([r.visible for r in sel])
        ax.plot(t, f, "o-" if i == 0 else "s--", ms=3, lw=1, color=f"C{i}", label=label)
        if i == 0:
            for tk, fk in zip(t, f, strict=True):
                if fk < VISIBLE_ENOUGH:
                    ax.axvspan(tk - spacing / 2, tk + spacing / 2, color="crimson", alpha=0.15,
                               lw=0)  # fmt: skip
    ax.axhline(VISIBLE_ENOUGH, color="0.5", ls=":", lw=0.8)
    ax.set_ylim(-0.05, 1.05)
    ax.set_ylabel((review.about or f"sees {review.target}").replace(" sees ", "\nsees "),
                  rotation=0, ha="right", va="center", fontsize=8)  # fmt: skip
    ax.legend(fontsize=7, loc="lower right", frameon=False, ncol=len(positions))
