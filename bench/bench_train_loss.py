"""Training cost of the loss's regularisers: the paper's (λ = 0.2, no needle term) against the
defaults (λ = 0.05, needle term μ = 10), in one run on the same timestamp.

    .venv/bin/egosurg sim eval-set --out out/evalset3 --phases intraoperative,turnover \\
        --sets 3 --eval-sets 0 --view-size 480x300          # once (docs/history/evaluation.md)
    .venv/bin/python bench/bench_train_loss.py [--evalset out/evalset3] [--steps 2000]

One intraoperative timestamp of the evaluation set, all 8 views at 480 px, the evaluation's
config (docs/evaluation_cpu.toml), EgoSurg w/o refinement, 2000 steps: each arm reconstructs
it from scratch, the paper's loss first. Prints a Markdown table of median ms per training
step, training seconds and the ratio to the paper's loss. The lighter opacity term keeps more
Gaussians above the rasterizer's alpha_min, so more fragments are composited per step.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

import reconstructor  # noqa: F401  (flushes denormals before torch starts its threads)
from protocol.formats.eval_set import EvalSet
from reconstructor.evaluation.methods import EvalSettings, method_config
from reconstructor.evaluation.runner import EvalSource
from reconstructor.pipeline import reconstruct

ARMS = {
    "paper (λ 0.2, no needle term)": {
        "train": {"opacity_reg_weight": 0.2, "anisotropy_reg_weight": 0.0}
    },
    "defaults (λ 0.05, needle term 10)": {},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evalset", default="out/evalset3")
    ap.add_argument("--scene", default="intraoperative")
    ap.add_argument("--steps", type=int, default=2000)
    args = ap.parse_args()
    source = EvalSource(EvalSet.read(args.evalset))
    scene = source.scene(args.scene)
    ts = source.timestamp(args.scene, scene.eval_sets[0])
    settings = EvalSettings(
        eval_set=args.evalset,
        steps=args.steps,
        train_width_px=480,
        config="docs/evaluation_cpu.toml",
        methods=("no-refinement",),
    )
    rows = []
    for name, overrides in ARMS.items():
        base = method_config(settings, "no-refinement", "all", scene.room_bounds_m)
        cfg = base.overridden(overrides, "bench")
        steps = reconstruct(ts, cfg, calibration=source.calibration(args.scene)).trainer.log.steps
        ms = 1000 * float(np.median([s.seconds for s in steps]))
        rows.append((name, ms, sum(s.seconds for s in steps)))
        print(f"{name}: median {ms:.1f} ms/step", flush=True)
    print(f"\n| loss | median ms/step | training s ({args.steps} steps) | ratio |")
    print("|---|---:|---:|---:|")
    for name, ms, total in rows:
        print(f"| {name} | {ms:.1f} | {total:.0f} | {ms / rows[0][1]:.2f} |")


if __name__ == "__main__":
    main()
