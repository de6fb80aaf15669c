"""Sealing throughput on one core: AES-256-GCM seal and open of one image, against the xxh3-64
checksum that every stored image already gets, on the same bytes in the same run.

Two payloads: a raw HD1200 image (1920 x 1200 x 3 bytes, the largest legal image) and a 300 KB
JPEG (about what a node sends at HD1200). The bytes are random: AES-GCM and xxh3 cost the same
on any content. Each row is the median of ``--repeats`` timed calls, the three operations
interleaved so that a busy neighbour slows them alike; MB is 10**6 bytes.

    .venv/bin/python bench/bench_sealing.py
    .venv/bin/python bench/bench_sealing.py --repeats 200
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import xxhash

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.sealing import PayloadContext, Sealer, new_data_key, new_session_uid

PAYLOADS = {"raw HD1200 (6.91 MB)": 1920 * 1200 * 3, "JPEG (300 KB)": 300_000}
CONTEXT = PayloadContext(
    field="image", camera_serial=41234567, row=1, side="left", capture_unix_ns=1
)


def _seconds(call: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    call()
    return time.perf_counter() - t0


def _row(name: str, size: int, repeats: int) -> tuple[str, float, float, float]:
    """(name, hash, seal, open) in MB/s for one payload size."""
    payload = os.urandom(size)
    sealer = Sealer(new_data_key(), new_session_uid())
    sealed = sealer.seal(payload, CONTEXT)
    times: dict[str, list[float]] = {"hash": [], "seal": [], "open": []}
    for _ in range(repeats):
        times["hash"].append(_seconds(lambda: xxhash.xxh3_64_intdigest(payload)))
        times["seal"].append(_seconds(lambda: sealer.seal(payload, CONTEXT)))
        times["open"].append(_seconds(lambda: sealer.open(sealed, CONTEXT)))
    rate = {k: size / 1e6 / statistics.median(v) for k, v in times.items()}
    return name, rate["hash"], rate["seal"], rate["open"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=60, help="timed calls per operation")
    args = parser.parse_args()
    print("| payload | xxh3-64 MB/s | seal MB/s | open MB/s | seal / xxh3 | open / xxh3 |")
    print("|---|---|---|---|---|---|")
    for name, size in PAYLOADS.items():
        _, hashed, sealed, opened = _row(name, size, args.repeats)
        print(
            f"| {name} | {hashed:,.0f} | {sealed:,.0f} | {opened:,.0f} | "
            f"{sealed / hashed:.2f} | {opened / hashed:.2f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
