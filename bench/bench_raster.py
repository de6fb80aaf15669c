"""Rasterizer speed: numba kernels against the PyTorch twin on the same inputs, in the same run.

    .venv/bin/python bench/bench_raster.py            # 960x600, 50k and 200k Gaussians
    .venv/bin/python bench/bench_raster.py --quick    # 480x300, 20k, fewer steps

The scene imitates a 3DGS initialisation from a fused point cloud: points on a back wall, a
floor and a few boxes 1-5 m in front of the camera (some outside the view), isotropic-ish
scales from the mean distance to the 3 nearest neighbours (5-20 mm at 200k), random
rotations, opacity 0.1-0.9. One step = forward and backward of the rasterizer (the gradient
of an L1 loss is given, so the loss itself is not timed).
JIT compilation goes to a fresh cache directory so that its cost is measured, and is reported
apart from the steps. Prints a Markdown table; BENCHMARKS.md records a run of it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

if "--use-cache" not in sys.argv:  # before numba is imported: measure compilation honestly
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="bench_raster_numba_")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from bench.malloc_tuning import tune_malloc

STAGES = ("project_fwd", "bin_sort", "raster_fwd", "raster_bwd", "project_bwd")


def make_scene(n: int, width: int, height: int, seed: int = 0) -> dict:
    """Gaussians on surfaces in front of a 70-degree camera, as a fused point cloud gives them."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    # (centre, axis u, axis v) of rectangles in camera-like world coordinates (y down, z ahead)
    quads = [
        ((0.0, 0.0, 5.0), (4.2, 0, 0), (0, 2.6, 0)),  # back wall, wider than the view
        ((0.0, 1.2, 3.0), (3.6, 0, 0), (0, 0, 2.0)),  # floor from z = 1 to 5
        ((0.6, 0.5, 2.6), (0.5, 0, 0), (0, 0.7, 0)),  # box 1 front face
        ((0.6, -0.2, 3.0), (0.5, 0, 0), (0, 0, 0.4)),  # box 1 top
        ((0.1, 0.5, 3.0), (0, 0, 0.4), (0, 0.7, 0)),  # box 1 side
        ((-0.9, 0.8, 1.6), (0.25, 0, 0), (0, 0.4, 0)),  # box 2 front face, close
        ((-0.9, 0.4, 1.85), (0.25, 0, 0), (0, 0, 0.25)),  # box 2 top
    ]
    areas = np.array([4 * np.linalg.norm(np.cross(u, v)) for _, u, v in quads])
    counts = rng.multinomial(n, areas / areas.sum())
    pts = []
    for (c, u, v), k in zip(quads, counts, strict=True):
        ab = rng.uniform(-1, 1, size=(k, 2))
        pts.append(np.asarray(c) + ab[:, :1] * np.asarray(u) + ab[:, 1:] * np.asarray(v))
    means = np.concatenate(pts) + rng.normal(0, 0.002, size=(n, 3))
    dist, _ = cKDTree(means).query(means, k=4)
    nn_scale = np.sqrt((dist[:, 1:] ** 2).mean(axis=1))
    log_scales = np.log(nn_scale)[:, None] + np.log(rng.uniform(0.6, 1.4, size=(n, 3)))
    colors = 0.5 + 0.3 * np.sin(means @ rng.normal(0, 3, size=(3, 3))) + rng.normal(0, 0.05, (n, 3))
    opacity = rng.uniform(0.1, 0.9, size=n)
    # camera: a little yaw and pitch, so nothing is axis-aligned on screen
    yaw, pitch = 0.08, -0.05
    rot_y = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rot_x = np.array(
        [[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]]
    )
    viewmat = np.eye(4)
    viewmat[:3, :3] = rot_x @ rot_y
    f = 0.5 * width / np.tan(np.radians(35.0))
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])

    def t32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return {
        "means_m": t32(means),
        "quats_wxyz": t32(rng.normal(size=(n, 4))),
        "log_scales": t32(log_scales),
        "opacity_logits": t32(np.log(opacity / (1 - opacity))),
        "colors": t32(colors),
        "viewmat": t32(viewmat),
        "K": t32(K),
        "width_px": width,
        "height_px": height,
        "background": t32([0.1, 0.1, 0.1]),
        "nn_scale_mm": (1e3 * np.percentile(nn_scale, 5), 1e3 * np.percentile(nn_scale, 95)),
    }


def _step(scene: dict, config, grad_image: torch.Tensor) -> float:
    """One forward and backward (the loss's gradient is given, so only the rasterizer counts)."""
    from reconstructor.raster import rasterize

    params = {k: scene[k].clone().requires_grad_(True) for k in _LEAVES}
    t0 = time.perf_counter()
    out = rasterize(
        **params, viewmat=scene["viewmat"], K=scene["K"], width_px=scene["width_px"],
        height_px=scene["height_px"], config=config,
    )  # fmt: skip
    out.image.backward(grad_image)
    return 1e3 * (time.perf_counter() - t0)


_LEAVES = ("means_m", "quats_wxyz", "log_scales", "opacity_logits", "colors", "background")


def _render(scene: dict, config) -> float:
    from reconstructor.raster import rasterize

    args = {k: scene[k] for k in (*_LEAVES, "viewmat", "K", "width_px", "height_px")}
    t0 = time.perf_counter()
    with torch.no_grad():
        rasterize(**args, config=config)
    return 1e3 * (time.perf_counter() - t0)


def _parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="480x300, 20k Gaussians")
    parser.add_argument("--steps", type=int, default=7, help="timed numba steps per size")
    parser.add_argument("--twin-steps", type=int, default=3, help="timed twin steps per size")
    parser.add_argument(
        "--twin-budget-s",
        type=float,
        default=300.0,
        help="measure the twin only once if its first step takes longer than this",
    )
    parser.add_argument("--use-cache", action="store_true", help="keep numba's on-disk cache")
    parser.add_argument("--default-malloc", action="store_true", help="do not tune glibc malloc")
    return parser.parse_args()


def main() -> None:
    args = _parse_args()

    import numba

    from reconstructor.raster import RasterConfig

    tuned = False if args.default_malloc else tune_malloc()
    width, height, sizes = (480, 300, [20_000]) if args.quick else (960, 600, [50_000, 200_000])
    steps = 3 if args.quick else args.steps
    fast, twin = RasterConfig(), RasterConfig(backend="torch")
    print(
        f"# {width}x{height}, {os.cpu_count()} CPUs, numba {numba.__version__} "
        f"({numba.get_num_threads()} threads, {numba.config.THREADING_LAYER}), torch "
        f"{torch.__version__} ({torch.get_num_threads()} threads), malloc tuned: {tuned}, "
        f"load average at start: {os.getloadavg()[0]:.1f}"
    )
    # untimed warm-up of the twin: its first call pays for imports and first-time dispatch
    small = make_scene(500, 64, 48)
    _step(small, twin, torch.zeros(48, 64, 3))
    rows = []
    for n in sizes:
        scene = make_scene(n, width, height)
        rows.append(_measure(scene, n, fast, twin, steps, args.twin_steps, args.twin_budget_s))
        print(
            f"done {n}: numba {rows[-1]['numba_ms']:.0f} ms, twin {rows[-1]['twin_ms']:.0f} ms",
            flush=True,
        )

    print(f"# load average at end: {os.getloadavg()[0]:.1f}")
    _print_tables(rows)


def _measure(
    scene: dict, n: int, fast, twin, steps: int, twin_steps: int, twin_budget_s: float
) -> dict:
    """One size: the first (compiling) numba step, then timed numba steps (all threads and one),
    renders, and the twin's steps (just one if it is slower than ``twin_budget_s``)."""
    import numba

    from reconstructor.raster import rasterize
    from reconstructor.raster.function import stage_times_ms

    width, height = scene["width_px"], scene["height_px"]
    threads = numba.get_num_threads()
    keys = (*_LEAVES, "viewmat", "K", "width_px", "height_px")
    # the gradient an L1 loss against a grey target would send (signs vary per pixel)
    signs = np.random.default_rng(1).choice([-1.0, 1.0], size=(height, width, 3))
    grad_image = torch.from_numpy(signs.astype(np.float32) / (3 * width * height))
    t0 = time.perf_counter()
    _step(scene, fast, grad_image)  # first call: compiles every kernel
    compile_s = time.perf_counter() - t0
    with torch.no_grad():
        out = rasterize(**{k: scene[k] for k in keys}, config=fast)
    n_vis = int((out.radii_px > 0).sum())
    step_ms, cpu_ms, stage = [], [], {s: [] for s in STAGES}
    for _ in range(steps):
        c0 = time.process_time()
        step_ms.append(_step(scene, fast, grad_image))
        cpu_ms.append(1e3 * (time.process_time() - c0))
        for s, v in stage_times_ms().items():
            stage[s].append(v)
    render_ms = [_render(scene, fast) for _ in range(steps)]
    numba.set_num_threads(1)
    one_thread_ms = [_step(scene, fast, grad_image) for _ in range(steps)]
    numba.set_num_threads(threads)
    twin_ms = [_step(scene, twin, grad_image)]
    if twin_ms[0] < twin_budget_s * 1e3:
        twin_ms += [_step(scene, twin, grad_image) for _ in range(twin_steps - 1)]
    twin_render_ms = _render(scene, twin)
    return {
        "n": n,
        "visible": n_vis,
        "nn_mm": scene["nn_scale_mm"],
        "compile_s": compile_s,
        "numba_ms": statistics.median(step_ms),
        "numba_min_ms": min(step_ms),
        "cpu_ms": statistics.median(cpu_ms),
        "one_thread_ms": statistics.median(one_thread_ms),
        "stages": {s: statistics.median(v) for s, v in stage.items() if v},
        "render_ms": statistics.median(render_ms),
        "twin_ms": statistics.median(twin_ms),
        "twin_steps": len(twin_ms),
        "twin_render_ms": twin_render_ms,
    }


def _print_tables(rows: list[dict]) -> None:
    """The Markdown tables: speed per size, then the numba step's stages."""
    print()
    print(
        "| Gaussians (visible) | NN scale p5-p95 | numba fwd+bwd ms, median (min) | CPU ms | "
        "1 thread ms | twin fwd+bwd ms (steps) | twin / numba | render fps numba (twin) | "
        "first call s (JIT) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['n']:,} ({r['visible']:,}) | {r['nn_mm'][0]:.0f}-{r['nn_mm'][1]:.0f} mm "
            f"| {r['numba_ms']:.0f} ({r['numba_min_ms']:.0f}) | {r['cpu_ms']:.0f} "
            f"| {r['one_thread_ms']:.0f} | {r['twin_ms']:,.0f} ({r['twin_steps']}) "
            f"| {r['twin_ms'] / r['numba_ms']:.0f}x "
            f"| {1e3 / r['render_ms']:.1f} ({1e3 / r['twin_render_ms']:.2f}) "
            f"| {r['compile_s']:.1f} |"
        )
    print()
    print("Median ms per stage of the numba step (other = Python, autograd, checks):")
    print()
    print("| Gaussians | " + " | ".join(STAGES) + " | other |")
    print("|---|" + "---:|" * (len(STAGES) + 1))
    for r in rows:
        st = r["stages"]
        other = r["numba_ms"] - sum(st.values())
        cells = " | ".join(f"{st.get(s, 0):.1f}" for s in STAGES)
        print(f"| {r['n']:,} | {cells} | {other:.1f} |")


if __name__ == "__main__":
    main()
