"""Observed versus inferred on the evaluation set's egocentric views: do the
pixels the observed map marks well observed render closer to the sim's exact view than the
pixels it marks inferred?

For each scene's evaluation instant: reconstruct it as ``egosurg evaluate``'s egocentric
protocol does (every sensor trains; ``--method``, ``--steps``, ``--train-width``,
``--config``), into a run folder; then, from that folder alone (``splats.ply`` and the cameras
it saved: ``summary.json``'s training views in its ``calibration.toml``), count each Gaussian's
views (reconstructor/replay/observed.py) and render every egocentric view and its observed map
from the person's eye (near plane 0.2 m, as the evaluation). Scores: PSNR over the pixels
marked well observed and over those marked inferred, per view and pooled (one PSNR of the
squared error summed over all views' pixels of the class), for each ``--min-views``; and the
same over textured pixels alone (the sim truth's grey level varies by more than
``--texture-sd`` (standard deviation in a 7 x 7 window): like against like, since a uniform wall
renders right whatever its geometry).

Example (the two-scene set of EVALUATION.md, "Observed versus inferred")::

    egosurg sim eval-set --out out/evalset3 --seed 3 --phases intraoperative,turnover \\
        --resolution SVGA --fps 15 --t-start 2 --sets 3 --eval-sets 0 --jpeg-quality 90 \\
        --view-size 480x300 --view-hfov 90
    python bench/bench_observed.py out/evalset3 --out out/observed --steps 2000 \\
        --train-width 480 --config docs/evaluation_cpu.toml

A run folder that already holds ``splats.ply`` is reused (``--retrain`` redoes it).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from protocol.formats.eval_set import EvalSet
from reconstructor.config import ReconstructConfig
from reconstructor.data.views import EYE_NEAR_M, novel_view
from reconstructor.evaluation.methods import EvalSettings, method_config
from reconstructor.evaluation.runner import EvalSource
from reconstructor.pipeline import reconstruct
from reconstructor.replay.observed import (
    ObservedConfig,
    observation_counts,
    observed_map,
    overlay,
    run_input_cameras,
)
from reconstructor.splats import ply
from reconstructor.splats.train import render

log = logging.getLogger("bench_observed")


def psnr_db(sse: float, n: float) -> float:
    """PSNR of a summed squared error over ``n`` pixels (3 channels, mean over them)."""
    return float("nan") if n == 0 else float(10 * np.log10(1.0 / max(sse / (3 * n), 1e-12)))


def local_sd(grey: np.ndarray, size_px: int = 7) -> np.ndarray:
    """(H, W) standard deviation of ``grey`` in a ``size_px`` square around each pixel."""
    mean = cv2.blur(grey, (size_px, size_px))
    return np.sqrt(np.maximum(cv2.blur(grey * grey, (size_px, size_px)) - mean * mean, 0.0))


def run_folder(args, source: EvalSource, scene, set_index: int) -> Path:
    """The scene's reconstruction at the instant, made (or reused) in its run folder."""
    folder = args.out / f"{scene.name}_set{set_index}"
    if (folder / "splats.ply").is_file() and not args.retrain:
        log.info("%s: reusing %s", scene.name, folder / "splats.ply")
        return folder
    settings = EvalSettings(
        eval_set=str(args.eval_set), methods=(args.method,), steps=args.steps,
        train_width_px=args.train_width, config=args.config or "",
    )  # fmt: skip
    cfg = method_config(settings, args.method, "all", scene.room_bounds_m)
    t0 = time.perf_counter()
    ts = source.timestamp(scene.name, set_index)
    reconstruct(ts, cfg, folder, calibration=source.calibration(scene.name))
    log.info("%s: reconstructed in %.0f s", scene.name, time.perf_counter() - t0)
    return folder


def picture(path: Path, truth: np.ndarray, img: np.ndarray, obs: np.ndarray) -> None:
    """sim's exact view | render | render with inferred content tinted | error (x4)."""
    u8 = lambda a: (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    err = np.clip(4 * np.abs(img - truth).mean(axis=2, keepdims=True), 0, 1).repeat(3, axis=2)
    tiles = [u8(truth), u8(img), overlay(u8(img), obs), u8(err)]
    labels = ["sim truth", "render", "inferred tinted", "|error| x4"]
    for tile, label in zip(tiles, labels, strict=True):
        cv2.putText(tile, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3)
        cv2.putText(tile, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=1)[:, :, ::-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("eval_set", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--method", default="egosurg", help="egosurg, no-refinement or image-only")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--train-width", type=int, default=480)
    p.add_argument("--config", default="", help="a base reconstruction config (TOML)")
    p.add_argument("--min-views", default="1,2,3,4", help="thresholds to score, e.g. 1,2,3,4")
    p.add_argument("--texture-sd", type=float, default=0.05, help="textured: local SD above")
    p.add_argument("--retrain", action="store_true")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    thresholds = [int(v) for v in args.min_views.split(",")]
    eval_set = EvalSet.read(args.eval_set)
    source = EvalSource(eval_set)
    # per threshold: [sse well, pixels well, sse inferred, pixels inferred]
    pooled = {m: [0.0, 0.0, 0.0, 0.0] for m in thresholds}
    textured = {m: [0.0, 0.0, 0.0, 0.0] for m in thresholds}  # the same, textured pixels only
    rows = []
    for scene in eval_set.scenes:
        for k in scene.eval_sets:
            views = [v for v in scene.views_at(k) if v.kind == "egocentric"]
            if not views:
                continue
            folder = run_folder(args, source, scene, k)
            g = ply.read_ply(folder / "splats.ply")
            raster = ReconstructConfig.read(folder / "config.toml").raster
            eye = dataclasses.replace(raster, near_m=max(raster.near_m, EYE_NEAR_M))
            counts = observation_counts(g, run_input_cameras(folder), raster)
            for view in views:
                truth = eval_set.image(view).astype(np.float32) / 255.0
                with torch.no_grad():
                    img = render(g, novel_view(view.camera), eye).image.clamp(0, 1).numpy()
                se = ((img - truth) ** 2).sum(axis=2)
                tex = local_sd(truth.mean(axis=2)) > args.texture_sd
                for m in thresholds:
                    cfg = ObservedConfig(min_views=m)
                    obs = observed_map(g, counts, view.camera, eye, cfg)
                    well = obs.well_observed(cfg)
                    for acc, sel in ((pooled[m], np.ones_like(tex)), (textured[m], tex)):
                        acc[0] += float(se[well & sel].sum())
                        acc[1] += float((well & sel).sum())
                        acc[2] += float(se[~well & sel].sum())
                        acc[3] += float((~well & sel).sum())
                    rows.append([scene.name, view.name, m, well.mean(),
                                 psnr_db(se[well].sum(), int(well.sum())),
                                 psnr_db(se[~well].sum(), int((~well).sum())),
                                 psnr_db(se.sum(), se.size)])  # fmt: skip
                    if m == 2:
                        picture(args.out / f"observed_{scene.name}_{view.name}.png",
                                truth, img, obs.observed)  # fmt: skip
    with (args.out / "observed.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scene", "view", "min_views", "well_observed_share", "psnr_well_db",
                    "psnr_inferred_db", "psnr_all_db"])  # fmt: skip
        w.writerows([[*r[:3], *(f"{x:.4f}" for x in r[3:])] for r in rows])
    lines = [
        "| min views | pixels well observed | PSNR well observed (dB) | PSNR inferred (dB) | "
        "views where well > inferred | textured pixels: PSNR well / inferred (dB) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for m, (s_w, n_w, s_i, n_i) in pooled.items():
        t = textured[m]
        per = [r for r in rows if r[2] == m and np.isfinite(r[4]) and np.isfinite(r[5])]
        better = sum(r[4] > r[5] for r in per)
        lines.append(
            f"| {m} | {100 * n_w / max(n_w + n_i, 1):.1f} % | {psnr_db(s_w, n_w):.2f} | "
            f"{psnr_db(s_i, n_i):.2f} | {better} of {len(per)} | "
            f"{psnr_db(t[0], t[1]):.2f} / {psnr_db(t[2], t[3]):.2f} |"
        )
    table = "\n".join(lines)
    (args.out / "observed.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
