"""``egosurg demo`` with each stage's CPU and wall time: where the demo (and the test that runs
it, tests/sim/test_cli.py) spends its time.

    .venv/bin/python bench/bench_demo_stages.py --out out/demo_stages --record-s 12 --steps 10

The arguments are the demo's own. A stage's CPU is this process's and its finished children's
(the agents, the recorder and every ``egosurg`` command the stage ran), from ``getrusage``, so
other jobs on a shared machine change it far less than the wall time. Prints the demo's own
output, then a Markdown table.
"""

from __future__ import annotations

import functools
import resource
import sys
import time

STAGES = (
    "stage_sim",
    "stage_capture",
    "stage_calibration",
    "stage_reconstruction",
    "stage_evaluation",
    "stage_batch",
    "stage_review",
    "stage_report",
)


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def main(argv: list[str]) -> int:
    import sim.demo as demo

    rows: list[tuple[str, float, float]] = []

    def timed(name: str):
        stage = getattr(demo, name)

        @functools.wraps(stage)
        def run(*args, **kwargs):
            cpu0, wall0 = _cpu_s(), time.perf_counter()
            try:
                return stage(*args, **kwargs)
            finally:
                rows.append((name, _cpu_s() - cpu0, time.perf_counter() - wall0))

        return run

    for name in STAGES:
        setattr(demo, name, timed(name))
    code = demo.main(argv)
    print("| stage | CPU (s) | wall (s) |")
    print("|---|---:|---:|")
    for name, cpu_s, wall_s in rows:
        print(f"| {name.removeprefix('stage_')} | {cpu_s:.1f} | {wall_s:.1f} |")
    total_cpu, total_wall = sum(r[1] for r in rows), sum(r[2] for r in rows)
    print(f"| all | {total_cpu:.1f} | {total_wall:.1f} |")
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
