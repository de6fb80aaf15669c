"""Wand calibration time for a 2-minute wand session at 30 fps on 2 cores.

    .venv/bin/python bench/bench_calibrate.py                      # record once, then time
    .venv/bin/python bench/bench_calibrate.py --max-sets 300,600   # compare set budgets
    .venv/bin/python bench/bench_calibrate.py --session wand.h5    # time a session you have

The session: the simulated rig (2 agents x 2 ZED X, HD1200, 30 fps, free-running clocks, 1 %
dropped frames, JPEG q92 4:4:4, world seed 7, phase "wand") recorded through the real agent and
recorder processes for ``--record-s`` seconds (default 120). The agents loop ``--content-s``
seconds of prerendered content (default 20 s: rendering 2 minutes of 8 HD1200 sensors would take
about two hours here), so the wand's path repeats; the recording starts with a loop, so the
session opens with the wand lying on the floor, as a real one does. The file has the real size
and structure of a 2-minute session (3600 sets, 28 800 images). It is kept in ``--out`` and
reused.

Each run is the real command, ``egosurg calibrate SESSION --wand wand.toml --out ...``, in a
subprocess, timed from start to exit (detection, solve, report and exports). The reference in the
same run is the floor under any calibration that reads the same images: decoding just those
images (the count the command reports), in 2 processes. The accuracy columns compare the result
with the simulator's true rig (after the best rigid fit, as in tests/calibration/test_e2e.py).
Prints a Markdown table; BENCHMARKS.md ("Wand calibration") records a run.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.wand import WandSpec
from protocol.session import SessionReader
from sim import World
from sim.deploy import SimRig, SimRigSpec, write_sim_rig
from sim.truth import calibration_errors, true_rig_calibration

ROOT = Path(__file__).resolve().parents[1]


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def record(out: Path, seed: int, record_s: float, content_s: float, fps: float) -> Path:
    spec = SimRigSpec(
        seed=seed,
        phase="wand",
        resolution="HD1200",
        fps=fps,
        content_fps=fps,
        prerender_s=content_s,
        drop_probability=0.01,
        jpeg_quality=92,
        planned_duration_min=record_s / 60.0,
        flush_interval_s=1.0,
    )
    files = write_sim_rig(out / "rig", spec)
    log(f"prerendering {content_s:.0f} s of content in the agents, then recording {record_s:.0f} s")
    with SimRig(files) as rig:
        rig.wait_streaming(timeout_s=7200)
        # start as the content loop starts again, so the session opens, as a real one does,
        # with the wand lying on the floor (calibration takes the floor from its first seconds)
        loop_ns = round(content_s * 1e9)
        sim_now_ns = time.time_ns() - files.epoch_unix_ns
        next_loop_ns = files.epoch_unix_ns + (sim_now_ns // loop_ns + 1) * loop_ns
        time.sleep(max(0.0, (next_loop_ns - time.time_ns()) / 1e9 - 0.3))
        rig.control("start", case="bench-wand")
        time.sleep(record_s)
        summary = rig.control("stop", timeout_s=120)
    path = Path(summary["file"])
    (out / "session.txt").write_text(f"{path}\n")
    log(f"recorded {path} ({path.stat().st_size / 1e9:.1f} GB)")
    return path


def _decode_rows(args: tuple) -> int:
    path, jobs = args
    cv2.setNumThreads(1)
    with SessionReader(path) as reader:
        for serial, row in jobs:
            for buf in reader.frame_bytes(serial, row):
                cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_COLOR)
    return len(jobs)


def decode_floor_s(session: Path, n_images: int, workers: int = 2) -> float:
    """Seconds to decode ``n_images`` of the session's images (pairs spread over it)."""
    with SessionReader(session) as reader:
        per_camera = {s: reader.frame_count(s) for s in reader.info.camera_serials}
    serials = list(per_camera)
    n_pairs = max(1, n_images // 2)
    jobs = []
    for k in range(n_pairs):
        serial = serials[k % len(serials)]
        jobs.append((serial, int(k * 7919 % per_camera[serial])))
    parts = [(str(session), jobs[w::workers]) for w in range(workers)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=workers) as pool:
        list(pool.map(_decode_rows, parts))
    return time.perf_counter() - t0


def calibrate(session: Path, wand: Path, out: Path, max_sets: int) -> dict:
    cmd = [
        *(sys.executable, "-m", "protocol.cli", "calibrate", str(session)),
        *("--wand", str(wand), "--out", str(out), "--max-sets", str(max_sets)),
    ]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"egosurg calibrate failed:\n{done.stdout}\n{done.stderr}")
    timing = re.search(
        r"timings: detection ([\d.]+) s \((\d+) images\), solve ([\d.]+) s, report ([\d.]+) s",
        done.stdout,
    )
    if timing is None:
        raise SystemExit(f"no timings line in the output of egosurg calibrate:\n{done.stdout}")
    verdict = re.search(r"verdict: (\w+)", done.stdout)
    return {
        "wall_s": wall,
        "detect_s": float(timing.group(1)),
        "images": int(timing.group(2)),
        "solve_s": float(timing.group(3)),
        "report_s": float(timing.group(4)),
        "verdict": verdict.group(1) if verdict else "?",
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench_calibrate")
    parser.add_argument("--session", type=Path, help="time this session instead of recording")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--record-s", type=float, default=120.0)
    parser.add_argument("--content-s", type=float, default=20.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--max-sets", default="300,600", help="comma-separated set budgets")
    parser.add_argument("--record-only", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    wand = args.out / "wand.toml"
    wand.write_text(WandSpec().to_toml())
    truth = None
    if args.session is not None:
        session = args.session
    elif (args.out / "session.txt").exists():
        session = Path((args.out / "session.txt").read_text().strip())
        log(f"reusing {session}")
    else:
        session = record(args.out, args.seed, args.record_s, args.content_s, args.fps)
    if args.session is None:
        truth = true_rig_calibration(World.from_seed(args.seed, phase="wand"))
    if args.record_only:
        return 0
    with SessionReader(session) as reader:
        n_sets = len(reader.sets().set_unix_ns)
        images = 2 * sum(reader.frame_count(s) for s in reader.info.camera_serials)
        span_s = (reader.sets().set_unix_ns[-1] - reader.sets().set_unix_ns[0]) / 1e9
    print(
        f"session: {session.name}, {span_s:.0f} s, {n_sets} sets, {images} images, "
        f"{session.stat().st_size / 1e9:.1f} GB; {os.cpu_count()} cores\n"
    )
    rows = []
    for budget in (int(v) for v in args.max_sets.split(",")):
        log(f"calibrating with --max-sets {budget}")
        res = calibrate(session, wand, args.out / f"sets{budget}" / "calibration.toml", budget)
        floor = decode_floor_s(session, res["images"])
        acc = ["n/a"] * 2
        cal = RigCalibration.read(args.out / f"sets{budget}" / "calibration.toml")
        if truth is not None:
            errors = calibration_errors(cal, truth)
            acc = [
                f"{max(e.rotation_deg for e in errors):.3f}",
                f"{max(e.translation_mm for e in errors):.2f}",
            ]
        q = cal.quality
        rows.append(
            [
                str(budget),
                str(res["images"]),
                f"{res['wall_s']:.1f}",
                f"{res['detect_s']:.1f}",
                f"{res['solve_s']:.1f}",
                f"{res['report_s']:.1f}",
                f"{floor:.1f}",
                f"{res['wall_s'] / floor:.2f}",
                f"{q['reprojection_px_mean']:.3f}",
                f"{q['wand_score']:.3f}",
                *acc,
                res["verdict"],
            ]
        )
        log(f"--max-sets {budget}: {res['wall_s']:.1f} s")
    header = [
        *("max sets", "images decoded", "calibrate s", "detection s", "solve s", "report s"),
        *("decode-only s", "calibrate / decode-only", "reproj. mean px", "wand score %"),
        *("max rot. err. deg", "max pos. err. mm", "verdict"),
    ]
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join(["---:"] * (len(header) - 1) + ["---"]) + "|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
