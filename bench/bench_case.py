"""Warm start against cold reconstruction of the same timestamps, in one run (issue 20).

A short sim case (the intraoperative phase, people moving) is reconstructed twice: every
timestamp cold (``--steps`` steps from stereo depth), and warm (the first cold, each later one
from the one before, updated from its own depth, ``--warm-steps`` steps). Both train on the left
sensors only and are scored on the held-out right sensors (the near-field protocol). It prints
CPU seconds per timestamp, their ratio and the near-field PSNR of each.

    .venv/bin/python bench/bench_case.py --sets 5 --steps 200 --warm-steps 25 --width 320
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from protocol.rig_calibration import RigCalibration
from reconstructor.case.cli import warm_config
from reconstructor.case.warm import WarmStartConfig, warm_seed
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.evaluation.metrics import psnr
from reconstructor.pipeline import Reconstruction, reconstruct
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sets", type=int, default=5)
    ap.add_argument("--steps", type=int, default=200, help="cold steps per timestamp")
    ap.add_argument("--warm-steps", type=int, default=25)
    ap.add_argument("--width", type=int, default=320, help="train_max_width_px")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_case_"))
    spec = EvalSetSpec(seed=args.seed, phases=("intraoperative",), sets=args.sets, eval_sets=(0,),
                       view_size_px=(64, 40))  # fmt: skip
    write_eval_set(root, spec)
    session = root / "intraoperative" / "session.h5"
    calibration = RigCalibration.read(root / "intraoperative" / "calibration.toml")
    base = ReconstructConfig(train_views="left", train_max_width_px=args.width)
    cold = dataclasses.replace(
        base,
        train=dataclasses.replace(base.train, warmup_steps=args.steps, refine_steps=0),
        auxiliary=dataclasses.replace(base.auxiliary, enabled=False),
    )
    warm_cfg = WarmStartConfig(steps=args.warm_steps)
    warm = warm_config(cold, warm_cfg)
    rows = []
    previous = None
    for k in range(args.sets):
        ts = load_timestamp(session, calibration, f"set:{k}")
        c0 = time.process_time()
        r_cold = reconstruct(ts, cold)
        cold_s = time.process_time() - c0
        counts: dict[str, int] = {}
        c0 = time.process_time()
        if previous is None:
            r_warm = r_cold
            warm_s = cold_s
        else:
            prev = previous

            def init(ts_, fused, depths, prev=prev, counts=counts):
                g, c = warm_seed(prev, ts_, fused, depths, warm_cfg, warm.init)
                counts.update(c)
                return g

            r_warm = reconstruct(ts, warm, init=init)
            warm_s = time.process_time() - c0
        previous = r_warm.gaussians
        rows.append((k, cold_s, warm_s, near_field_psnr(r_cold), near_field_psnr(r_warm), counts))
    print(f"\nsim seed {args.seed}, intraoperative, {args.sets} consecutive sets at 15 fps, "
          f"width {args.width}px, cold {args.steps} steps, warm {args.warm_steps} steps, "
          f"{torch.get_num_threads()} threads")  # fmt: skip
    print("| set | cold CPU s | warm CPU s | ratio | cold PSNR | warm PSNR | kept/dropped/added")
    print("|---|---|---|---|---|---|---")
    for k, cs, ws, cp, wp, c in rows:
        kda = f"{c.get('kept', '-')}/{c.get('dropped', '-')}/{c.get('added', '-')}"
        print(f"| {k} | {cs:.1f} | {ws:.1f} | {ws / cs:.3f} | {cp:.2f} | {wp:.2f} | {kda} |")
    later = rows[1:]
    if later:
        ratio = sum(r[2] for r in later) / sum(r[1] for r in later)
        dpsnr = np.mean([r[4] - r[3] for r in later])
        print(f"\nwarm timestamps: CPU time {ratio:.3f} of cold; near-field PSNR {dpsnr:+.2f} dB")


if __name__ == "__main__":
    main()
