"""Warm start against cold reconstruction of the same timestamps, in one run.

A sim case (the intraoperative phase, people moving) is reconstructed twice: every timestamp
cold, with the evaluation's EgoSurg settings (``--steps`` split 25 % warm-up and 75 %
refinement with the guided refiner's auxiliary views, ``--train-width``, ``--config``), and as
one warm chain (the first timestamp's cold model, each later one from the one before, updated
from its own stereo depth, ``--warm-steps`` steps: ``reconstructor/case/warm.py``). Both train
on the left sensors and are scored on the held-out right ones (the near-field protocol). Each
timestamp's row is printed when it is done: process CPU seconds of each, their ratio, the
near-field PSNR of each and their difference, and where the warm timestamp's time went.

The comparison, at the evaluation's settings (EVALUATION.md)::

    nice -n 10 .venv/bin/python bench/bench_case.py --sets 6 --steps 2000 --train-width 480 \\
        --config docs/evaluation_cpu.toml

Quick look (no auxiliary views, short schedules)::

    .venv/bin/python bench/bench_case.py --sets 3 --steps 200 --warm-steps 25 --train-width 320 \\
        --no-refiner
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from protocol.formats.eval_set import EvalSet
from protocol.formats.rig_calibration import RigCalibration
from reconstructor.case.warm import WarmStartConfig, seed_from_previous, warm_config
from reconstructor.case.work import limit_threads
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.evaluation.methods import EvalSettings, method_config
from reconstructor.evaluation.metrics import psnr
from reconstructor.pipeline import Reconstruction, reconstruct
from reconstructor.splats import ply
from reconstructor.splats.train import render
from sim.eval_set import EvalSetSpec, write_eval_set


def near_field_psnr(result: Reconstruction) -> float:
    cfg = result.config
    scores = []
    with torch.no_grad():
        for view in result.held_out_views:
            out = render(result.gaussians, view, cfg.raster, torch.zeros(3))
            scores.append(psnr(out.image.clamp(0, 1), view.image, view.mask))
    return float(np.mean(scores))


def cold_config(args: argparse.Namespace, bounds: tuple[float, ...]) -> ReconstructConfig:
    """The evaluation's EgoSurg config (``method_config``), or without auxiliary views."""
    settings = EvalSettings(steps=args.steps, train_width_px=args.train_width, config=args.config)
    cfg = method_config(settings, "egosurg", "left", bounds)
    if args.no_refiner:
        cfg = dataclasses.replace(cfg, auxiliary=dataclasses.replace(cfg.auxiliary, enabled=False))
    return cfg


def cpu_timed(fn, *a, **k):  # type: ignore[no-untyped-def]
    c0 = time.process_time()
    out = fn(*a, **k)
    return out, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sets", type=int, default=6, help="consecutive timestamps (15 fps)")
    ap.add_argument("--steps", type=int, default=2000, help="cold steps (25 %% warm-up)")
    ap.add_argument("--warm-steps", type=int, default=WarmStartConfig.steps)
    ap.add_argument("--train-width", type=int, default=480, help="train_max_width_px")
    ap.add_argument("--config", default="docs/evaluation_cpu.toml", help="base config (TOML)")
    ap.add_argument("--no-refiner", action="store_true", help="cold without auxiliary views")
    ap.add_argument("--eval-set", default="", help="reuse this sim evaluation set folder")
    ap.add_argument("--threads", type=int, default=0, help="torch/numba threads (0: default)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--save-models", default="", help="folder: each model as cold_<k>/warm_<k>.ply")
    args = ap.parse_args()
    limit_threads(args.threads)
    if args.eval_set:
        eval_set = EvalSet.read(args.eval_set)
    else:
        root = Path(tempfile.mkdtemp(prefix="bench_case_"))
        spec = EvalSetSpec(seed=args.seed, phases=("intraoperative",), sets=args.sets,
                           eval_sets=(0,), instants=1, view_size_px=(64, 40))  # fmt: skip
        eval_set = write_eval_set(root, spec)
    scene = next(s for s in eval_set.scenes if s.phase == "intraoperative")
    session = eval_set.path(scene.session)
    calibration = RigCalibration.read(eval_set.path(scene.calibration))
    cold = cold_config(args, scene.room_bounds_m)
    warm_cfg = WarmStartConfig(steps=args.warm_steps)
    warm = warm_config(cold, warm_cfg)
    print(f"sim {eval_set.description}; cold: {cold.train.warmup_steps} + "
          f"{cold.train.refine_steps} steps, auxiliary views "
          f"{'on' if cold.auxiliary.enabled else 'off'}, width {args.train_width} px; "
          f"{warm_cfg.describe()}; {torch.get_num_threads()} threads", flush=True)  # fmt: skip
    print("| set | cold CPU s | warm CPU s | warm / cold | cold PSNR | warm PSNR | warm - cold "
          "| Gaussians cold / warm | kept / dropped / faded / added | warm s: stereo, "
          "fusion+seed, training |", flush=True)  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|---|", flush=True)
    rows = []
    previous = None
    for k in range(args.sets):
        ts = load_timestamp(session, calibration, f"set:{k}")
        r_cold, cold_s = cpu_timed(reconstruct, ts, cold, calibration=calibration)
        counts: dict[str, int] = {}
        if previous is None:
            r_warm, warm_s = r_cold, cold_s
        else:

            def init(ts_, fused, depths, prev=previous, counts=counts):  # type: ignore[no-untyped-def]
                seed = seed_from_previous(prev, ts_, fused, depths, warm_cfg, warm.init)
                counts.update(seed.counts)
                return seed.gaussians

            r_warm, warm_s = cpu_timed(reconstruct, ts, warm, calibration=calibration, init=init)
        previous = r_warm.gaussians
        if args.save_models:
            out = Path(args.save_models)
            out.mkdir(parents=True, exist_ok=True)
            ply.write_ply(out / f"cold_{k}.ply", r_cold.gaussians)
            ply.write_ply(out / f"warm_{k}.ply", r_warm.gaussians)
        row = (k, cold_s, warm_s, near_field_psnr(r_cold), near_field_psnr(r_warm))
        rows.append(row)
        t = r_warm.timings_s
        kda = "/".join(str(counts.get(n, "-")) for n in ("kept", "dropped", "faded", "added"))
        stages = (f"{t.get('stereo', 0):.1f}, {t.get('fusion_init', 0):.1f}, "
                  f"{t.get('warmup', 0) + t.get('refinement', 0):.1f}")  # fmt: skip
        print(f"| {k} | {cold_s:.1f} | {warm_s:.1f} | {warm_s / cold_s:.3f} | {row[3]:.2f} | "
              f"{row[4]:.2f} | {row[4] - row[3]:+.2f} | {r_cold.gaussians.num} / "
              f"{r_warm.gaussians.num} | {kda} | {stages if counts else '(cold)'} |",
              flush=True)  # fmt: skip
    later = rows[1:]
    if later:
        ratio = sum(r[2] for r in later) / sum(r[1] for r in later)
        dpsnr = np.mean([r[4] - r[3] for r in later])
        print(f"\nwarm timestamps 1-{len(rows) - 1}: CPU time {ratio:.3f} of cold (goal: at "
              f"most 0.125); near-field PSNR {dpsnr:+.2f} dB (goal: within 0.3 dB)")  # fmt: skip


if __name__ == "__main__":
    main()
