"""Scores of an evaluation run, their summaries (mean ± SD over scenes), and the files they go to.

Per protocol, in ``OUT/<protocol>/``:
- ``scores.csv``: one row per scored image (image protocols) or per sequence and camera
  (temporal);
- ``table.csv`` and ``table.md``: the summary, mean ± sample SD over scenes (a scene's score is
  the mean over its views), with the run's settings in the Markdown header;
- ``png/``: side-by-side pictures, truth | each method.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from reconstructor.evaluation.lpips import NO_WEIGHTS
from reconstructor.evaluation.methods import EvalSettings

RECORDED = "recorded"  # the temporal reference row: the recorded right images themselves
# the temporal frames scored against the recorded right images (near-field scores of each frame):
# a row that is steady because it is blurred or frozen shows here
FIDELITY = "temporal-fidelity"
IMAGE_METRICS = (("psnr_db", "PSNR (dB) ↑"), ("ssim", "SSIM ↑"), ("lpips", "LPIPS ↓"))
TEMPORAL_METRICS = (
    ("t_psnr_db", "t-PSNR (dB) ↑"),
    ("t_ssim", "t-SSIM ↑"),
    ("t_lpips", "t-LPIPS ↓"),
    ("flicker", "Flicker ↓"),
)
HIGHER_IS_BETTER = {"psnr_db": True, "ssim": True, "lpips": False}
HIGHER_IS_BETTER |= {"t_psnr_db": True, "t_ssim": True, "t_lpips": False, "flicker": False}


@dataclass(frozen=True)
class ImageScore:
    protocol: str
    method: str
    phase: str
    scene: str  # the unit of mean ± SD: a timestamp, or (timestamp, view) for egocentric views
    view: str
    psnr_db: float
    ssim: float
    lpips: float | None
    holes: float | None = None  # share of the compared pixels the method drew nothing on
    drawn_psnr_db: float | None = None  # PSNR over the pixels it drew (methods with holes)


@dataclass(frozen=True)
class TemporalScore:
    method: str
    phase: str
    scene: str  # "<sequence> <camera>": the unit of mean ± SD
    view: str
    t_psnr_db: float
    t_ssim: float
    t_lpips: float | None
    flicker: float
    pairs: int


@dataclass
class EvalResults:
    settings: EvalSettings
    image_scores: list[ImageScore] = field(default_factory=list)
    temporal_scores: list[TemporalScore] = field(default_factory=list)
    recon_seconds: dict[str, list[float]] = field(default_factory=dict)  # method -> per run
    refiner: str = ""  # the refiner's own description, from a run that used it
    wall_s: float = 0.0  # every job's time, those of earlier sittings (resumed) included
    resumed_jobs: int = 0  # timestamps loaded from an earlier sitting's records
    # the libraries that made the jobs' depth stages, in words -> how many jobs (a job whose
    # depth came from two makers counts under both)
    depth_made_by: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Stat:
    mean: float
    sd: float  # sample SD over scenes; nan for a single scene
    n: int


@dataclass(frozen=True)
class Row:
    method: str
    phase: str  # "" when the row spans phases
    stats: dict[str, Stat | None]  # metric -> summary, None when not measured (no LPIPS)
    scenes: int


def stat(values: Sequence[float]) -> Stat:
    v = np.asarray(values, np.float64)
    if len(v) == 0:
        return Stat(math.nan, math.nan, 0)
    sd = float(np.std(v, ddof=1)) if len(v) > 1 and np.all(np.isfinite(v)) else math.nan
    return Stat(float(np.mean(v)), sd, len(v))


def _per_scene(scores: Sequence, metric: str) -> list[float] | None:
    by_scene: dict[str, list[float]] = {}
    for s in scores:
        value = getattr(s, metric)
        if value is None:
            return None
        by_scene.setdefault(s.scene, []).append(value)
    return [float(np.mean(v)) for v in by_scene.values()]


def summary_rows(results: EvalResults, protocol: str, *, by_phase: bool = False) -> list[Row]:
    """One row per method (and per phase with ``by_phase``), methods in the paper's order."""
    if protocol == "temporal":
        scores: list = results.temporal_scores
        metrics = [m for m, _ in TEMPORAL_METRICS]
        methods = [*results.settings.methods, RECORDED]
    else:
        scores = [s for s in results.image_scores if s.protocol == protocol]
        metrics = [m for m, _ in IMAGE_METRICS]
        methods = list(results.settings.methods)
    phases = list(dict.fromkeys(s.phase for s in scores)) if by_phase else [""]
    rows = []
    for phase in phases:
        for method in methods:
            chosen = [s for s in scores if s.method == method and (not phase or s.phase == phase)]
            if not chosen:
                continue
            stats: dict[str, Stat | None] = {}
            for m in metrics:
                per_scene = _per_scene(chosen, m)
                stats[m] = None if per_scene is None else stat(per_scene)
            rows.append(Row(method, phase, stats, len({s.scene for s in chosen})))
    return rows


def fmt(s: Stat | None, metric: str) -> str:
    """Like the paper: PSNR to 0.1 dB, the others to three decimals without the leading zero."""
    if s is None:
        return NO_WEIGHTS
    if not math.isfinite(s.mean):
        return "inf" if s.mean > 0 else "n/a"

    def one(v: float) -> str:
        if metric.endswith("psnr_db"):
            return f"{v:.1f}"
        text = f"{v:.3f}"
        return text[1:] if text.startswith("0.") else text

    return one(s.mean) if math.isnan(s.sd) else f"{one(s.mean)} ± {one(s.sd)}"


def markdown_table(results: EvalResults, protocol: str, *, by_phase: bool = False) -> str:
    metrics = TEMPORAL_METRICS if protocol == "temporal" else IMAGE_METRICS
    head = ["Phase"] if by_phase else []
    head += ["Method", *(label for _, label in metrics), count_label(protocol)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in summary_rows(results, protocol, by_phase=by_phase):
        cells = [row.phase] if by_phase else []
        cells.append(method_label(results, row.method))
        cells += [fmt(row.stats[m], m) for m, _ in metrics]
        cells.append(str(row.scenes))
        lines.append("| " + " | ".join(cells) + " |")
    note = holes_note(results, protocol)
    return "\n".join(lines) + (f"\n\n{note}" if note else "")


def holes_note(results: EvalResults, protocol: str) -> str:
    """One sentence per method that leaves pixels empty (depth reprojection): the share of the
    compared pixels it drew nothing on, mean ± SD over the protocol's units."""
    parts = []
    for method in results.settings.methods:
        chosen = [
            s for s in results.image_scores
            if s.protocol == protocol and s.method == method and s.holes is not None
        ]  # fmt: skip
        per_scene = _per_scene(chosen, "holes") if chosen else None
        if per_scene:
            st = stat([100 * v for v in per_scene])
            sd = "" if math.isnan(st.sd) else f" ± {st.sd:.1f}"
            drawn = _per_scene(chosen, "drawn_psnr_db")
            over = (
                f"; over the pixels it drew, PSNR {fmt(stat(drawn), 'psnr_db')} dB" if drawn else ""
            )
            parts.append(
                f"{method_label(results, method)} leaves {st.mean:.1f}{sd} % of the compared "
                f"pixels empty (holes, scored as black){over}."
            )
    return " ".join(parts)


def role_of(score: ImageScore) -> str:
    """The person an egocentric view belongs to (views are named ``<role>@<set>``)."""
    return score.view.split("@")[0]


def breakdown_table(results: EvalResults, protocol: str, by: str) -> str:
    """PSNR of each method, mean ± SD over the views of each ``phase`` or ``role``: where the
    protocol's mean comes from (the paper reports only the mean over all)."""
    scores = [s for s in results.image_scores if s.protocol == protocol]
    key = (lambda s: s.phase) if by == "phase" else role_of
    groups = list(dict.fromkeys(key(s) for s in scores))
    methods = [m for m in results.settings.methods if any(s.method == m for s in scores)]
    head = [{"phase": "Phase", "role": "Person (role)"}[by]]
    head += [*(f"{method_label(results, m)} PSNR" for m in methods), "views"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        cells, n = [g], 0
        for m in methods:
            chosen = [s for s in scores if s.method == m and key(s) == g]
            per_scene = _per_scene(chosen, "psnr_db") or []
            cells.append(fmt(stat(per_scene), "psnr_db"))
            n = max(n, len(per_scene))
        lines.append("| " + " | ".join([*cells, str(n)]) + " |")
    return "\n".join(lines)


def instant_of(score: ImageScore) -> str:
    """The timestamp an egocentric view was scored at (its ``scene`` is ``<instant>/<view>``)."""
    return score.scene.split("/")[0]


def instants_table(results: EvalResults, protocol: str) -> str:
    """Each method's PSNR and SSIM as the paper reports them: each instant's mean over its
    views, then mean ± SD over the instants."""
    scores = [s for s in results.image_scores if s.protocol == protocol]
    methods = [m for m in results.settings.methods if any(s.method == m for s in scores)]
    lines = ["| Method | PSNR (dB) ↑ | SSIM ↑ | instants |", "|---|---|---|---|"]
    for m in methods:
        by_instant: dict[str, list[ImageScore]] = {}
        for s in scores:
            if s.method == m:
                by_instant.setdefault(instant_of(s), []).append(s)
        cells = [method_label(results, m)]
        for metric in ("psnr_db", "ssim"):
            means = [float(np.mean([getattr(s, metric) for s in v])) for v in by_instant.values()]
            cells.append(fmt(stat(means), metric))
        lines.append("| " + " | ".join([*cells, str(len(by_instant))]) + " |")
    return "\n".join(lines)


def egocentric_breakdowns(results: EvalResults) -> str:
    """Over instants (when there are several), per phase (when the views span several) and per
    role, as Markdown; "" for one of each."""
    scores = [s for s in results.image_scores if s.protocol == "egocentric"]
    parts = []
    if len({instant_of(s) for s in scores}) > 1:
        parts.append("Over instants (each instant's mean over its views, then mean ± SD over the "
                     "instants, as the paper reports):\n\n"
                     + instants_table(results, "egocentric"))  # fmt: skip
    if len({s.phase for s in scores}) > 1:
        parts.append("Per phase (PSNR in dB, mean ± SD over its views):\n\n"
                     + breakdown_table(results, "egocentric", "phase"))  # fmt: skip
    if len({role_of(s) for s in scores}) > 1:
        parts.append("Per person (PSNR in dB, mean ± SD over their views):\n\n"
                     + breakdown_table(results, "egocentric", "role"))  # fmt: skip
    return "\n\n".join(parts)


FIDELITY_TITLE = (
    "The same frames against the recorded right images (PSNR, SSIM per timestamp, mean ± SD "
    "over the sequence's timestamps):"
)


def count_label(protocol: str) -> str:
    """What the mean ± SD runs over."""
    return {"temporal": "sequences x cameras", "egocentric": "views", FIDELITY: "timestamps"}.get(
        protocol, "scenes"
    )


def method_label(results: EvalResults, key: str) -> str:
    if key == RECORDED:
        return "recorded right images (reference)"
    return results.settings.label(key)


def write_protocol(results: EvalResults, protocol: str, out_dir: Path, title: str) -> str:
    """scores.csv, table.csv and table.md of one protocol; returns the Markdown."""
    out_dir.mkdir(parents=True, exist_ok=True)
    by_phase = protocol == "phases"
    if protocol == "temporal":
        _write_csv(out_dir / "scores.csv", results.temporal_scores)
    else:
        _write_csv(
            out_dir / "scores.csv", [s for s in results.image_scores if s.protocol == protocol]
        )
    rows = summary_rows(results, protocol, by_phase=by_phase)
    with open(out_dir / "table.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        metrics = [m for m, _ in (TEMPORAL_METRICS if protocol == "temporal" else IMAGE_METRICS)]
        w.writerow(["phase", "method", *(f"{m}_{k}" for m in metrics for k in ("mean", "sd")), "n"])
        for r in rows:
            vals: list[str] = []
            for m in metrics:
                s = r.stats[m]
                vals += ["", ""] if s is None else [f"{s.mean:.6g}", f"{s.sd:.6g}"]
            w.writerow([r.phase, r.method, *vals, r.scenes])
    md = (
        f"## {title}\n\nSettings: {results.settings.describe()}.\n\n"
        f"{markdown_table(results, protocol, by_phase=by_phase)}\n"
    )
    if protocol == "egocentric" and (more := egocentric_breakdowns(results)):
        md += f"\n{more}\n"
    fidelity = [s for s in results.image_scores if s.protocol == FIDELITY]
    if protocol == "temporal" and fidelity:
        _write_csv(out_dir / "fidelity_scores.csv", fidelity)
        md += f"\n{FIDELITY_TITLE}\n\n{markdown_table(results, FIDELITY)}\n"
    (out_dir / "table.md").write_text(md)
    return md


def _write_csv(path: Path, rows: Sequence) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        if not rows:
            return
        names = list(rows[0].__dataclass_fields__)
        w.writerow(names)
        for r in rows:
            cells = []
            for n in names:
                v = getattr(r, n)
                cells.append("" if v is None else f"{v:.6g}" if isinstance(v, float) else str(v))
            w.writerow(cells)


def _tile(image: np.ndarray, label: str, width_px: int | None = None) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    tile = np.ascontiguousarray(img[:, :, ::-1])
    if width_px and tile.shape[1] != width_px:
        h = round(tile.shape[0] * width_px / tile.shape[1])
        tile = cv2.resize(tile, (width_px, h), interpolation=cv2.INTER_AREA)
    scale = max(0.35, tile.shape[1] / 1200)
    y = int(12 + 24 * scale)
    cv2.putText(tile, label, (6, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3)
    cv2.putText(tile, label, (6, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1)
    return tile


def side_by_side(path: Path, tiles: Sequence[tuple[str, np.ndarray]]) -> None:
    """One row: each (label, image), images (H, W, 3) float in [0, 1] or uint8 RGB."""
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate([_tile(img, label) for label, img in tiles], axis=1))


def filmstrip(path: Path, rows: Sequence[tuple[str, Sequence[np.ndarray]]], width_px: int) -> None:
    """One row per (label, frames): consecutive frames left to right, each ``width_px`` wide."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = []
    for label, frames in rows:
        tiles = [_tile(f, f"{label} #{k}", width_px) for k, f in enumerate(frames)]
        lines.append(np.concatenate(tiles, axis=1))
    cv2.imwrite(str(path), np.concatenate(lines, axis=0))


def mean_seconds(results: EvalResults) -> dict[str, float]:
    """Mean seconds per reconstruction of each method that trained."""
    return {m: float(np.mean(v)) for m, v in results.recon_seconds.items() if v}
