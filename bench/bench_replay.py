"""Replay throughput at 960x600 with a model switch at every frame (the goal: at least 10
frames/s on 2 cores with preloading on; the rate with preloading off beside it).

    .venv/bin/python bench/bench_replay.py [--timestamps 20] [--gaussians-from .gpu/scene.npz]

The case is made here, not reconstructed (that takes hours on 2 cores): ``--timestamps`` models
0.1 s apart, each the sim scene's 144,000 Gaussians of ``tests/gpu_scene.py`` (a cold
reconstruction holds 194-228k) moved by a few millimetres so that every file differs, written as
a case folder the replay reads like any other (PLYs, checksums, ``case.json``). The replay runs
at 10 frames per second of case time, so every frame shows the next model: the worst case for
model switching. Both runs write their MP4 (H.264 through PyAV), as `egosurg replay` does.
Prints a Markdown table (BENCHMARKS.md, "Replay").
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from protocol.formats.trajectory import Keyframe, Trajectory
from reconstructor.case.index import CaseIndex, Entry, checksum_file
from reconstructor.replay.path import CameraPath
from reconstructor.replay.run import ReplayConfig, replay
from reconstructor.splats import ply


def make_case(folder: Path, n: int, scene_file: str) -> None:
    from tests.gpu_scene import build, load_scene

    scene = load_scene(Path(scene_file))[0] if scene_file else build()[0]
    g0 = scene.gaussians
    (folder / "models").mkdir(parents=True)
    rng = np.random.default_rng(0)
    entries = []
    for k in range(n):
        g = g0.detach_clone()
        g.means_m += torch.from_numpy(rng.normal(0, 0.002, g.means_m.shape).astype(np.float32))
        name = f"t{0.1 * k:09.3f}"
        path = ply.write_ply(folder / "models" / f"{name}.ply", g)
        digest, size = checksum_file(path)
        entries.append(Entry(
            name=name, t_s=0.1 * k, set_index=k, model=f"models/{name}.ply", xxh3_64=digest,
            bytes=size, status="done", gaussians=g.num,
        ))  # fmt: skip
    CaseIndex(
        session="bench", session_started_unix_ns=0, config_hash="bench", warm_start=False,
        created_unix_ns=time.time_ns(), timestamps=tuple(entries),
    ).write(folder)  # fmt: skip


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--timestamps", type=int, default=20)
    p.add_argument("--gaussians-from", default="", help="a tests/gpu_scene.py .npz (else the sim)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_replay_") as tmp:
        folder = Path(tmp) / "case"
        t0 = time.perf_counter()
        make_case(folder, args.timestamps, args.gaussians_from)
        print(f"case: {args.timestamps} models in {time.perf_counter() - t0:.0f} s", flush=True)
        end = 0.1 * (args.timestamps - 1)
        path = CameraPath(Trajectory(name="walk", keyframes=(
            Keyframe(time_s=0.0, eye_m=(2.5, -2.0, 1.7), look_at_m=(0.0, 0.0, 1.0)),
            Keyframe(time_s=end, eye_m=(1.0, -2.6, 1.6), look_at_m=(0.0, 0.0, 1.0)),
        )))  # fmt: skip
        rows = []
        for preload in (True, False):
            cfg = ReplayConfig(fps=10.0, size_px=(960, 600), preload=preload)
            stats = replay(folder, path, Path(tmp) / f"replay_{preload}.mp4", cfg)
            rows.append((preload, stats))
            print(f"preload {preload}: {stats.fps:.1f} frames/s", flush=True)
    print(f"\n{os.cpu_count()} cores; {args.timestamps} models of 144,000 Gaussians, a switch "
          "at every frame, 960x600\n")  # fmt: skip
    print("| preloading | frames | models | frames/s | waiting on models, s |")
    print("|---|---:|---:|---:|---:|")
    for preload, s in rows:
        print(f"| {'on' if preload else 'off'} | {s.frames} | {s.models} | {s.fps:.1f} | "
              f"{s.load_wait_s:.2f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
