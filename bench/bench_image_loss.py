"""The training step's image loss, forward and backward: the fused kernels against their twin.

One step's loss at the trainer's image size: (1 - α) · L1 + α · (1 - SSIM) of a render against
its target over a mask, with the random-background fill, then the gradient in the render. The
twin is ``ssim.l1`` + ``ssim.ssim`` under autograd (what the trainer used before); the
fused path is ``reconstructor.splats.image_loss``. Both run interleaved in the same process;
the table gives medians and the ratio.

    .venv/bin/python bench/bench_image_loss.py               # 960x600, 15 steps each
    .venv/bin/python bench/bench_image_loss.py --size 480x300
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.malloc_tuning import tune_malloc
from reconstructor.splats.image_loss import image_loss


def _case(h: int, w: int) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(0)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    target = torch.stack([xx, yy, (xx * 9).floor() % 2 * 0.7 + 0.1], dim=2)
    target = (target + 0.03 * torch.rand(h, w, 3, generator=gen)).clamp(0, 1)
    rendered = (target.roll(3, dims=1) + 0.05 * torch.randn(h, w, 3, generator=gen)).clamp(0, 1)
    mask = torch.ones(h, w)
    mask[:4], mask[:, -6:] = 0, 0  # an undistortion border
    return rendered, target, mask, torch.rand(3, generator=gen)


def _step_ms(backend: str, case: tuple[torch.Tensor, ...]) -> float:
    rendered, target, mask, fill = case
    x = rendered.clone().requires_grad_(True)
    t0 = time.perf_counter()
    loss, _, _ = image_loss(x, target, mask, 0.2, fill, backend=backend)
    loss.backward()
    return 1e3 * (time.perf_counter() - t0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="960x600", help="WIDTHxHEIGHT")
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument(
        "--default-malloc", action="store_true", help="keep glibc's malloc settings (see below)"
    )
    args = parser.parse_args()
    tuned = False if args.default_malloc else tune_malloc()
    w, h = (int(v) for v in args.size.lower().split("x"))
    case = _case(h, w)
    for backend in ("numba", "torch"):  # warm-up: JIT, caches, allocator
        _step_ms(backend, case)
    times: dict[str, list[float]] = {"numba": [], "torch": []}
    for _ in range(args.steps):
        for backend in times:
            times[backend].append(_step_ms(backend, case))
    load = os.getloadavg()[0]
    print(
        f"\nimage loss forward + backward at {w}x{h}, {torch.get_num_threads()} torch threads, "
        f"load average {load:.1f}, {args.steps} interleaved steps each, "
        f"malloc {'tuned (bench/malloc_tuning.py)' if tuned else 'default'}"
    )
    print(f"{'path':<32}{'median ms':>10}{'min ms':>10}")
    for backend, label in (("torch", "twin (metrics.l1 + ssim)"), ("numba", "fused (image_loss)")):
        print(f"{label:<32}{statistics.median(times[backend]):>10.1f}{min(times[backend]):>10.1f}")
    ratio = statistics.median(times["torch"]) / statistics.median(times["numba"])
    print(f"twin / fused: {ratio:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
