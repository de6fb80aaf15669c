"""Seconds per timestamp for the reconstructor's schedule at SVGA, on this machine's CPU.

One simulated OR timestamp (four ZED X at SVGA, 960x600, rendered by sim/ with sensor noise),
the sim's true calibration, the default config: stereo depth, hole filling, fusion,
initialisation, then training on the eight views with the paper's losses. Prints a table with
each stage's time, the training's ms per step split into rendering (forward + backward of the
rasterizer) and the rest (loss, SSIM, Adam), and the total for the paper's 2000 steps, measured
or, with ``--steps N``, extrapolated from N steps (the table says which).

    .venv/bin/python bench/bench_reconstruct.py              # the full 2000 steps
    .venv/bin/python bench/bench_reconstruct.py --steps 100  # quicker, extrapolated
    .venv/bin/python bench/bench_reconstruct.py --model out/bench_reconstruct/splats.ply
        # no reconstruction: a trained model's step, taken apart, and its render fps

After a run it also times a few more steps part by part (``--part-steps``), and renders of
the model from the input views without gradients (the novel-view render path).

Goal: at most 10 minutes per timestamp on 2 cores; the paper's RTX 4090 takes about 2.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.camera import Resolution
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import SensorFrame, Timestamp
from reconstructor.pipeline import reconstruct
from reconstructor.splats.train import TrainConfig, Trainer
from sim import World

PAPER_STEPS = 2000
GOAL_S = 600.0


def sim_timestamp(seed: int, t_s: float) -> Timestamp:
    world = World.from_seed(seed, phase="intraoperative")
    frames = []
    for unit in world.rig:
        for side in ("left", "right"):
            render = world.render_sensor(unit.index, side, t_s, "SVGA")
            frames.append(
                SensorFrame(
                    camera=unit.sensor(side, "SVGA"),
                    camera_serial=unit.serial,
                    side=side,
                    image_rgb=render.image_rgb,
                    capture_unix_ns=0,
                )
            )
    return Timestamp(
        session=Path(f"sim seed {seed}"),
        set_index=0,
        set_unix_ns=0,
        t_s=t_s,
        frames=tuple(frames),
        missing_serials=(),
        resolution=Resolution.SVGA,
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=PAPER_STEPS, help="training steps to run")
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--out", default="out/bench_reconstruct")
    parser.add_argument(
        "--part-steps", type=int, default=12, help="extra steps timed part by part after the run"
    )
    parser.add_argument(
        "--model",
        type=Path,
        help="a splat PLY of this seed's timestamp: skip the reconstruction, time only its "
        "steps part by part and its renders",
    )
    args = parser.parse_args()
    ts = sim_timestamp(args.seed, 1.0)
    if args.model is not None:
        return time_model(ts, args.model, args.part_steps)
    warm = min(500, args.steps)
    cfg = ReconstructConfig(
        train=TrainConfig(warmup_steps=warm, refine_steps=args.steps - warm, log_every_steps=100)
    )
    t0 = time.perf_counter()
    rec = reconstruct(ts, cfg, Path(args.out))
    total_s = time.perf_counter() - t0
    steps = rec.trainer.log.steps
    step_ms = np.array([s.seconds for s in steps]) * 1000
    train_s = float(step_ms.sum() / 1000)
    setup_s = total_s - train_s
    per_step_ms = float(np.median(step_ms[min(5, len(step_ms) - 1) :]))
    full_s = setup_s + PAPER_STEPS * per_step_ms / 1000
    measured = args.steps == PAPER_STEPS
    print(
        f"\nreconstruction of one SVGA timestamp ({platform.processor() or 'cpu'}, "
        f"{os.cpu_count()} cores), {rec.gaussians.num} Gaussians, {len(rec.train_views)} views"
    )
    print(f"{'stage':<34}{'seconds':>10}")
    for name, sec in rec.timings_s.items():
        print(f"{name:<34}{sec:>10.1f}")
    print(f"{'training ms per step (median)':<34}{per_step_ms:>10.0f}")
    label = "measured" if measured else f"extrapolated from {args.steps} steps"
    print(f"{'total for 2000 steps (' + label + ')':<34}{full_s:>10.0f}")
    print(
        f"goal: <= {GOAL_S:.0f} s -> {'met' if full_s <= GOAL_S else 'NOT met'} "
        f"({full_s / GOAL_S:.2f}x the goal; the paper's GPU: about 120 s)"
    )
    print(f"final training loss {rec.trainer.log.mean_loss():.4f}")
    print_parts_and_renders(rec.trainer, rec.train_views, args.part_steps, "after the run")
    return 0


def time_model(ts: Timestamp, model: Path, part_steps: int) -> int:
    """A trained model's training step, part by part, and its render fps."""
    from reconstructor.pipeline import make_views
    from reconstructor.splats.ply import read_ply
    from reconstructor.splats.train import scene_extent_m

    cfg = ReconstructConfig().resolved(ts.frames[0].camera.intrinsics.width_px)
    views, _ = make_views(ts, cfg)
    gaussians = read_ply(model)
    trainer = Trainer(gaussians, cfg.train, cfg.raster, scene_extent_m(views))
    for view in views[:3]:  # compile and warm up
        trainer.step(view)
    print(f"model {model}: {gaussians.num} Gaussians, {len(views)} views")
    print_parts_and_renders(trainer, views, part_steps, "on this model")
    return 0


def print_parts_and_renders(trainer: Trainer, views: list, steps: int, when: str) -> None:
    parts = step_parts_ms(trainer, views, steps)
    print(f"\nwhere a step's time goes (median of {steps} extra steps, {when}):")
    for name, ms in parts.items():
        print(f"  {name:<40}{ms:>8.1f} ms")
    render_ms = render_times_ms(trainer, views, 2 * len(views))
    print(
        f"render without gradients, {views[0].width_px}x{views[0].height_px} (the input views, "
        f"median of {len(render_ms)}): {np.median(render_ms):.1f} ms, "
        f"{1000 / np.median(render_ms):.1f} fps"
    )


def render_times_ms(trainer: Trainer, views: list, n: int) -> list[float]:
    """Wall ms of ``n`` renders of the model from ``views`` under ``torch.no_grad()``."""
    from reconstructor.splats.train import render

    times = []
    with torch.no_grad():
        for k in range(n):
            t0 = time.perf_counter()
            render(trainer.g, views[k % len(views)], trainer.raster, torch.rand(3))
            times.append(1e3 * (time.perf_counter() - t0))
    return times


def step_parts_ms(trainer: Trainer, views: list, steps: int) -> dict[str, float]:
    """A training step taken apart (the same calls as ``Trainer.step``), timed part by part."""
    from reconstructor.raster.function import stage_times_ms
    from reconstructor.splats.image_loss import image_loss
    from reconstructor.splats.train import render

    cfg = trainer.config
    rows: dict[str, list[float]] = {}
    for k in range(steps):
        view = views[k % len(views)]
        bg = torch.rand(3)
        t0 = time.perf_counter()
        out = render(trainer.g, view, trainer.raster, bg)
        t1 = time.perf_counter()
        term, _, _ = image_loss(out.image, view.image, view.mask, cfg.ssim_weight, bg)
        loss = term + cfg.opacity_reg_weight * torch.sigmoid(trainer.g.opacity_logits).mean()
        t2 = time.perf_counter()
        trainer.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        t3 = time.perf_counter()
        trainer.optimizer.step()
        t4 = time.perf_counter()
        stages = stage_times_ms()
        for name, ms in (
            ("rasterizer forward (all stages)", 1e3 * (t1 - t0)),
            ("  of which projection", stages["project_fwd"]),
            ("  of which binning and depth sort", stages["bin_sort"]),
            ("  of which compositing, forward", stages["raster_fwd"]),
            ("image loss + opacity term, forward", 1e3 * (t2 - t1)),
            ("backward (loss, rasterizer, projection)", 1e3 * (t3 - t2)),
            ("  of which compositing, backward", stages["raster_bwd"]),
            ("  of which projection, backward", stages["project_bwd"]),
            ("Adam", 1e3 * (t4 - t3)),
            ("whole step", 1e3 * (t4 - t0)),
        ):
            rows.setdefault(name, []).append(ms)
    return {name: float(np.median(v)) for name, v in rows.items()}


if __name__ == "__main__":
    raise SystemExit(main())
