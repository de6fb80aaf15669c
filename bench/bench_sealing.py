"""Sealing throughput on one core: AES-256-GCM seal and open of one image, against the xxh3-64
checksum that every stored image already gets, on the same bytes in the same run.

Two payloads: a raw HD1200 image (1920 x 1200 x 3 bytes, the largest legal image) and a 300 KB
JPEG (about what a node sends at HD1200). The bytes are random: AES-GCM and xxh3 cost the same
on any content. Each row is the median of ``--repeats`` timed calls, the three operations
interleaved so that a busy neighbour slows them alike; MB is 10**6 bytes.

    .venv/bin/python bench/bench_sealing.py
    .venv/bin/python bench/bench_sealing.py --repeats 200

A second table: ``SessionWriter`` appending real-size JPEG pairs (2 x 325 kB, random bytes) from
one camera with a flush every 15 frames, plaintext and sealed alternating in one run (best of
``--writer-rounds``): images/s, CPU per image (the whole process, and the appending thread
alone: in the recorder, its session-queue thread), and the ratio. The reference rig needs 240
images/s.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import xxhash

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.sealing import (
    PayloadContext,
    Sealer,
    generate_identity,
    new_data_key,
    new_session_uid,
)
from protocol.session import CameraInfo, SessionWriter

WRITER_ROWS = 300
WRITER_CAMERA = CameraInfo(
    camera_serial=101,
    node_id="orin-a",
    resolution="HD1200",
    width=1920,
    height=1200,
    fps_nominal=30.0,
    encoding="jpeg",
)

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


def _jpeg_like(seed: int, size: int) -> bytes:
    """Random bytes framed as a JPEG (the writer checks the markers)."""
    body = random.Random(seed).randbytes(size - 4)
    return b"\xff\xd8" + body + b"\xff\xd9"


def append_seconds(path: Path, recipients: list, rows: int) -> tuple[float, float, float]:
    """(wall, appending thread's CPU, process CPU) seconds to append ``rows`` pairs of 2 x 325 kB
    images to a new session, flushing every 15 rows as the recorder does. The appending thread is
    the recorder's session-queue thread."""
    pair = (_jpeg_like(1, 325_000), _jpeg_like(2, 325_000))
    with SessionWriter(
        path,
        session_name="bench",
        case_metadata={},
        cameras=[WRITER_CAMERA],
        tolerance_ns=16_666_666,
        software_version="bench",
        started_unix_ns=1_770_000_000_000_000_000,
        recipients=recipients,
    ) as w:
        started, mine, cpu = time.perf_counter(), time.thread_time(), time.process_time()
        for row in range(rows):
            w.append_frame(
                WRITER_CAMERA.camera_serial,
                left=pair[0],
                right=pair[1],
                capture_unix_ns=1_770_000_000_000_000_000 + row,
                host_receive_unix_ns=0,
                recorder_receive_unix_ns=0,
                frame_index=row,
                seq=row,
                ptp_offset_ns=0,
                ptp_locked=True,
            )
            if row % 15 == 14:
                w.flush()
        w.flush()
        return (
            time.perf_counter() - started,
            time.thread_time() - mine,
            time.process_time() - cpu,
        )


def _append_rate(path: Path, recipients: list) -> tuple[float, float, float]:
    """(images/s, CPU microseconds per image of the process, and of the appending thread) of
    appending WRITER_ROWS pairs to a new session."""
    wall, mine, cpu = append_seconds(path, recipients, WRITER_ROWS)
    images = 2 * WRITER_ROWS
    return images / wall, cpu / images * 1e6, mine / images * 1e6


def writer_table(rounds: int) -> None:
    """Plaintext against sealed appends, alternating, best of ``rounds``."""
    recipient = generate_identity("bench").recipient
    rates: dict[str, list[tuple[float, float, float]]] = {"plaintext": [], "sealed": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):
            for name, recipients in (("plaintext", []), ("sealed", [recipient])):
                path = Path(tmp) / f"{name}-{k}.h5"
                rates[name].append(_append_rate(path, recipients))
                path.unlink()
    print()
    print(
        "| session writer, 2 x 325 kB pairs | images/s | CPU us per image | of it on the "
        "appending thread | rate / plaintext |"
    )
    print("|---|---|---|---|---|")
    best = {name: max(r for r, _, _ in v) for name, v in rates.items()}
    for name, v in rates.items():
        cpu, mine = min(c for _, c, _ in v), min(t for _, _, t in v)
        print(f"| {name} | {best[name]:,.0f} | {cpu:.0f} | {mine:.0f} | "
              f"{best[name] / best['plaintext']:.2f} |")  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=60, help="timed calls per operation")
    parser.add_argument("--writer-rounds", type=int, default=3, help="0 skips the writer table")
    args = parser.parse_args()
    print("| payload | xxh3-64 MB/s | seal MB/s | open MB/s | seal / xxh3 | open / xxh3 |")
    print("|---|---|---|---|---|---|")
    for name, size in PAYLOADS.items():
        _, hashed, sealed, opened = _row(name, size, args.repeats)
        print(
            f"| {name} | {hashed:,.0f} | {sealed:,.0f} | {opened:,.0f} | "
            f"{sealed / hashed:.2f} | {opened / hashed:.2f} |"
        )
    if args.writer_rounds:
        writer_table(args.writer_rounds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
