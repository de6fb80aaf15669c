"""The session writer's sealing, one change at a time: plaintext, sealed with both images on the
appending thread, and sealed with the left image on the sealing thread at once (the default), in
one process, interleaved round by round; microseconds per image of wall time, of the appending
thread's CPU (in the recorder, its session-queue thread) and of the whole process's CPU, min and
median over the rounds.

    .venv/bin/python bench/bench_sealing_threads.py --rounds 8

The one-thread variant raises the writer's size threshold for the second thread above any frame
(``protocol.session.sealed._PARALLEL_MIN_BYTES``): the code measured is otherwise the product's.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_sealing import append_seconds

from protocol.sealing import generate_identity
from protocol.session import sealed as sealed_module

ROWS = 150
MODES = {"plaintext": None, "sealed, one thread": 1 << 40, "sealed, two threads": 64 << 10}


def _run(path: Path, recipients: list) -> tuple[float, float, float]:
    """Microseconds per image: wall, the appending thread's CPU, the process's CPU."""
    k = 2 * ROWS / 1e6
    wall, mine, cpu = append_seconds(path, recipients, ROWS)
    return wall / k, mine / k, cpu / k


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=8)
    args = parser.parse_args()
    recipient = generate_identity("bench").recipient
    default = sealed_module._PARALLEL_MIN_BYTES
    results: dict[str, list[tuple[float, float, float]]] = {m: [] for m in MODES}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rounds):
            for mode, threshold in MODES.items():
                sealed_module._PARALLEL_MIN_BYTES = default if threshold is None else threshold
                path = Path(tmp) / f"{k}.h5"
                results[mode].append(_run(path, [] if threshold is None else [recipient]))
                path.unlink()
    sealed_module._PARALLEL_MIN_BYTES = default
    print("| writer | wall us/image | appending thread CPU us/image | process CPU us/image |")
    print("|---|---|---|---|")
    for mode, rows in results.items():
        cells = [
            f"{min(r[i] for r in rows):.0f}, {statistics.median(r[i] for r in rows):.0f}"
            for i in range(3)
        ]
        print(f"| {mode} | {' | '.join(cells)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
