"""The CUDA backend (gsplat) against the CPU backend (numba) on one sim timestamp, same machine.

    python bench/bench_gpu.py                      # on a machine with CUDA and gsplat
    EGOSURG_GPU_SCENE=scene.npz python bench/bench_gpu.py  # one without open3d (gpu_scene.py)
    python bench/bench_gpu.py --cpu-only --steps 2000 --json bench/results/gpu_cpu_reference.json

The scene is ``tests/gpu_scene.py``'s: the rig's four left sensors at SVGA (960x600) to train on,
the four right sensors held out, Gaussians seeded from the true depth of every 4th pixel (144k). The
schedule is the reconstructor's (``TrainConfig``: 500 warm-up + 1500 steps; no auxiliary views,
whose refiner runs on the CPU whatever the backend). Measured, each in the same run:

- the full schedule on the GPU (data uploaded once, the Trainer's own loop), seconds;
- ms per step over the first ``--cpu-steps`` steps on both backends (same model, same views):
  their ratio, and the CPU schedule it implies;
- renders of the trained model at 960x600 without gradients, frames per second, both backends;
- a warm-started timestamp (t + 1 s): 250 steps from the trained model on the new views,
  including the Trainer's setup and upload, seconds;
- held-out PSNR of the trained model, rendered by gsplat and by numba; with ``--reference``, the
  CPU run's PSNR after the same schedule (made by ``--cpu-only``; the sim is deterministic).

Prints a Markdown table (BENCHMARKS.md, "GPU backend") and writes ``--json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numba
import torch

from reconstructor.case.warm import WarmStartConfig
from reconstructor.evaluation.metrics import psnr
from reconstructor.raster import RasterConfig
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import TrainConfig, Trainer, render

CPU = RasterConfig()
GPU = RasterConfig(backend="gsplat")


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def held_out_psnr(g: Gaussians, views, raster: RasterConfig) -> float:
    with torch.no_grad():
        return statistics.fmean(
            psnr(render(g, v, raster).image.clamp(0, 1), v.image, v.mask) for v in views
        )


def train(scene, raster: RasterConfig, steps: int, start: Gaussians | None = None, views=None):
    """A copy of the scene's (or ``start``'s) Gaussians trained ``steps`` steps; seconds."""
    g = (start or scene.gaussians).detach_clone()
    cfg = TrainConfig(warmup_steps=min(500, steps), refine_steps=max(0, steps - 500))
    _sync()
    t0 = time.perf_counter()
    trainer = Trainer(g, cfg, raster, scene.extent_m)
    trainer.run(views or scene.train, steps)
    _sync()
    return g, time.perf_counter() - t0


def ms_per_step(scene, raster: RasterConfig, steps: int) -> float:
    train(scene, raster, 3)  # compile / load kernels, first allocations
    _, s = train(scene, raster, steps)
    return 1e3 * s / steps


def render_fps(g: Gaussians, views, raster: RasterConfig, frames: int) -> float:
    with torch.no_grad():
        render(g, views[0], raster)
        _sync()
        t0 = time.perf_counter()
        for k in range(frames):
            render(g, views[k % len(views)], raster)
        _sync()
    return frames / (time.perf_counter() - t0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=2000, help="the schedule's steps (2000)")
    p.add_argument("--cpu-steps", type=int, default=20, help="steps timed on both backends (20)")
    p.add_argument("--frames", type=int, default=300, help="GPU renders timed (300)")
    p.add_argument("--cpu-only", action="store_true", help="train the schedule on the CPU only")
    p.add_argument("--reference", help="a --cpu-only run's JSON: its PSNR beside the GPU's")
    p.add_argument("--json", help="write the results here")
    p.add_argument("--cpu-schedule", action="store_true", help="also time the CPU's schedule")
    p.add_argument("--compare", action="store_true", help="first, gsplat vs numba per scene")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")  # step progress

    from tests.gpu_scene import scene_for_gpu

    t0 = time.perf_counter()
    scene, later = scene_for_gpu()
    n = scene.gaussians.num
    print(f"scene: {n} Gaussians, {len(scene.train)} views at 960x600 "
          f"({time.perf_counter() - t0:.0f} s to build)", flush=True)  # fmt: skip
    res: dict[str, object] = {
        "gaussians": n, "steps": args.steps, "cpu_threads": numba.get_num_threads(),
        "cpu": platform.processor() or platform.machine(), "torch": torch.__version__,
    }  # fmt: skip
    if args.cpu_only:
        g, s = train(scene, CPU, args.steps)
        res.update(cpu_schedule_s=s, cpu_psnr_numba=held_out_psnr(g, scene.held_out, CPU))
        print(f"CPU schedule {s:.0f} s, held-out PSNR {res['cpu_psnr_numba']:.2f} dB")
    else:
        import gsplat

        res.update(gpu=torch.cuda.get_device_name(), gsplat=gsplat.__version__)
        if args.compare:
            try:  # a table for the docs: the timings below must not depend on it
                res["compare"] = compare_table()
            except Exception as e:
                print(f"comparison failed: {type(e).__name__}: {e}", flush=True)
        gpu_ms = ms_per_step(scene, GPU, args.cpu_steps)
        cpu_ms = ms_per_step(scene, CPU, args.cpu_steps)
        print(f"first {args.cpu_steps} steps: GPU {gpu_ms:.1f} ms/step, CPU {cpu_ms:.0f} ms/step",
              flush=True)  # fmt: skip
        g, s = train(scene, GPU, args.steps)
        print(f"GPU schedule: {s:.1f} s", flush=True)
        if args.cpu_schedule:
            g_ref, cpu_s = train(scene, CPU, args.steps)
            cpu_psnr = held_out_psnr(g_ref, scene.held_out, CPU)
            res.update(cpu_schedule_s=cpu_s, cpu_psnr_numba=cpu_psnr)
            print(f"CPU schedule: {cpu_s:.1f} s", flush=True)
        gpu_fps = render_fps(g, scene.held_out, GPU, args.frames)
        g_cpu = g.to(device="cpu")
        cpu_fps = render_fps(g_cpu, scene.held_out, CPU, 10)
        warm_steps = WarmStartConfig().steps
        _, warm_s = train(scene, GPU, warm_steps, start=g, views=later)
        res.update(
            gpu_ms_per_step=gpu_ms, cpu_ms_per_step=cpu_ms, gpu_schedule_s=s,
            gpu_render_fps=gpu_fps, cpu_render_fps=cpu_fps, warm_steps=warm_steps,
            gpu_warm_s=warm_s, gpu_psnr_gsplat=held_out_psnr(g, scene.held_out, GPU),
            gpu_psnr_numba=held_out_psnr(g_cpu, scene.held_out, CPU),
        )  # fmt: skip
        if args.reference and Path(args.reference).is_file() and not args.cpu_schedule:
            ref = json.loads(Path(args.reference).read_text())
            res["cpu_psnr_numba"] = ref["cpu_psnr_numba"]
            res["cpu_schedule_s_reference_machine"] = ref["cpu_schedule_s"]
        print_table(res, args.cpu_steps)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res, indent=2))
    return 0


def compare_table() -> dict[str, dict[str, float]]:
    """gsplat against numba on the rasterizer tests' scenes (the differences
    tests/reconstructor/test_raster_gsplat.py bounds), printed as a table."""
    from tests.reconstructor.test_raster import SCENES, make_scene
    from tests.reconstructor.test_raster_gsplat import compare

    rows = {name: compare(make_scene(**kw)) for name, kw in SCENES.items()}
    print("| scene | image mean / max | alpha mean / max | depth rel. max | worst gradient |")
    print("|---|---:|---:|---:|---|")
    for name, d in rows.items():
        worst = max((k for k in d if k.startswith("grad_")), key=lambda k: d[k])
        print(f"| {name} | {d['image_mean']:.1e} / {d['image_max']:.1e} | {d['alpha_mean']:.1e} "
              f"/ {d['alpha_max']:.1e} | {d['depth_rel_max']:.1e} | {worst[5:]} "
              f"{d[worst]:.1e} |", flush=True)  # fmt: skip
    return rows


def print_table(r: dict, cpu_steps: int) -> None:
    steps = r["steps"]
    cpu_sched = r.get("cpu_schedule_s") or r["cpu_ms_per_step"] * steps / 1e3
    rows = [
        (f"ms per step (first {cpu_steps} steps)", r["gpu_ms_per_step"], r["cpu_ms_per_step"]),
        (f"{steps}-step SVGA schedule, s", r["gpu_schedule_s"], cpu_sched),
        ("render 960x600, frames/s", r["gpu_render_fps"], r["cpu_render_fps"]),
        (f"warm timestamp ({r['warm_steps']} steps), s", r["gpu_warm_s"], float("nan")),
    ]
    print(f"\n{r['gpu']}, gsplat {r['gsplat']}, torch {r['torch']}; CPU: numba on "
          f"{r['cpu_threads']} threads; {r['gaussians']} Gaussians\n")  # fmt: skip
    print("| measure | GPU (gsplat) | CPU (numba) | CPU / GPU |")
    print("|---|---:|---:|---:|")
    for name, gpu, cpu in rows:
        ratio = cpu / gpu if name.startswith(("ms", f"{steps}")) else gpu / cpu
        est = "schedule" in name and "cpu_schedule_s" not in r
        cpu_txt = "" if cpu != cpu else f"{cpu:.1f}" + (" (est.)" if est else "")
        ratio_txt = "" if ratio != ratio else f"{ratio:.0f}x"
        print(f"| {name} | {gpu:.2f} | {cpu_txt} | {ratio_txt} |")
    print(f"\nheld-out PSNR after {steps} steps on the GPU: {r['gpu_psnr_gsplat']:.2f} dB rendered "
          f"by gsplat, {r['gpu_psnr_numba']:.2f} dB by numba", end="")  # fmt: skip
    if "cpu_psnr_numba" in r:
        d = r["gpu_psnr_numba"] - r["cpu_psnr_numba"]
        print(f"; trained on the CPU: {r['cpu_psnr_numba']:.2f} dB (GPU - CPU {d:+.2f} dB)")
    else:
        print()


if __name__ == "__main__":
    raise SystemExit(main())
