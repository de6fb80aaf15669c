"""A simulated rig's prerendering: how long its agents take to stream HD1200 wand content (what
the calibration test's fixture and the demo's stage 3 wait for), with the renderer's threads
shared out among the agents (``sim.deploy.render_threads_per_agent``, the default) against a
thread per core in every agent (Numba's own default), alternated in one run.

    .venv/bin/python bench/bench_sim_rig.py [--prerender-s 4] [--repeats 2]

Prints a Markdown table; BENCHMARKS.md ("Simulator") records a run of it. Each run starts the
real agent and recorder processes (``sim.deploy.SimRig``) on a rig of the calibration test's
settings (seed 5, wand phase, HD1200, 10 fps, every frame rendered at its own time, JPEG 92)
with a shorter loop of content, and times the start until every camera streams; the agents'
CPU seconds are read from the processes just before they stop.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import psutil

from sim.deploy import SimRig, SimRigSpec, render_threads_per_agent, write_sim_rig


def one_run(directory: Path, prerender_s: float, render_threads: int) -> tuple[float, float]:
    """(seconds until every camera streams, agents' CPU seconds) of one fresh rig."""
    spec = SimRigSpec(
        plaintext=True,
        seed=5,
        phase="wand",
        resolution="HD1200",
        fps=10.0,
        content_fps=10.0,
        prerender_s=prerender_s,
        drop_probability=0.01,
        jpeg_quality=92,
    )
    files = write_sim_rig(directory, spec)
    rig = SimRig(files, render_threads=render_threads)
    t0 = time.perf_counter()
    try:
        rig.start()
        rig.wait_streaming(timeout_s=1800)
        wall_s = time.perf_counter() - t0
        cpu_s = 0.0
        for name, proc in rig.procs.items():
            if name.startswith("agent"):
                times = psutil.Process(proc.pid).cpu_times()
                cpu_s += times.user + times.system
    finally:
        rig.close()
    return wall_s, cpu_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--prerender-s", type=float, default=4.0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    split = render_threads_per_agent(2)
    modes = ((f"shared out ({split} per agent)", split), ("a thread per core in each agent", 0))
    results: dict[str, list[tuple[float, float]]] = {name: [] for name, _ in modes}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for name, threads in modes:
                run = Path(tmp) / f"{r}-{threads}"
                results[name].append(one_run(run, args.prerender_s, threads))
    frames = 4 * round(args.prerender_s * 10)
    ref_wall = statistics.median(w for w, _ in results[modes[1][0]])
    ref_cpu = statistics.median(c for _, c in results[modes[1][0]])
    print(f"{frames} HD1200 stereo pairs prerendered by 2 agents (4 cameras), {args.repeats} runs")
    print()
    print("| renderer threads | to streaming (s) | agents' CPU (s) | vs reference (medians) |")
    print("|---|---:|---:|---|")
    for name, _ in modes:
        wall = statistics.median(w for w, _ in results[name])
        cpu = statistics.median(c for _, c in results[name])
        note = "reference" if name == modes[1][0] else f"{ref_wall / wall:.2f}x sooner"
        note += "" if name == modes[1][0] else f", {ref_cpu / cpu:.2f}x less CPU"
        print(f"| {name} | {wall:.1f} | {cpu:.1f} | {note} |")


if __name__ == "__main__":
    main()
