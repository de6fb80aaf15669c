"""A finished case (``egosurg reconstruct --every ... --train-views left``) scored timestamp by
timestamp against the cameras it did not train on, with its seconds and stored bytes.

Each model is loaded as stored (a keyframe, or a warm timestamp rebuilt from its chain's
changes) and rendered into that instant's held-out right cameras; the table has one row per
timestamp and a summary of keyframes (cold) against warm ones from the same run: CPU seconds,
MB stored, near-field PSNR, and PSNR by position in the chain (does a long chain drift?).

    .venv/bin/python bench/bench_case_scores.py out/case60/case [--csv out/case60/scores.csv]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from protocol.formats.rig_calibration import RigCalibration
from reconstructor.case.index import CaseIndex
from reconstructor.case.storage import load_model
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.pipeline import make_views

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_case_storage import near_field_psnr  # one scoring for both benches


def _mean(values: list[float]) -> str:
    return f"{np.mean(values):.2f} ± {np.std(values):.2f}" if values else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("case", type=Path)
    ap.add_argument("--csv", type=Path, help="write the per-timestamp rows here too")
    args = ap.parse_args()
    index = CaseIndex.read(args.case)
    config = ReconstructConfig.read(args.case / "config.toml")
    if config.train_views != "left":
        raise SystemExit(
            f"{args.case} trained on every camera: nothing is held out to score against "
            "(reconstruct with --train-views left)"
        )
    calibration = RigCalibration.read(args.case / "calibration.toml")
    rows = []
    since_key = 0
    print("| timestamp | from | Gaussians | s | MB stored | held-out PSNR (dB) |")
    print("|---|---|---:|---:|---:|---:|")
    for e in index.timestamps:
        if e.status != "done":
            continue
        since_key = 0 if not e.warm_from else since_key + 1
        ts = load_timestamp(index.session, calibration, f"set:{e.set_index}")
        _, held = make_views(ts, config)
        score = near_field_psnr(load_model(args.case, e), held, config.raster)
        rows.append(
            {"name": e.name, "t_s": e.t_s, "warm_from": e.warm_from, "chain_position": since_key,
             "gaussians": e.gaussians, "seconds": e.seconds, "mb": e.bytes / 1e6, "psnr_db": score}
        )  # fmt: skip
        r = rows[-1]
        print(
            f"| {e.name} | {e.warm_from or 'cold'} | {e.gaussians} | {e.seconds:.1f} | "
            f"{r['mb']:.2f} | {score:.2f} |",
            flush=True,
        )
    cold = [r for r in rows if not r["warm_from"]]
    warm = [r for r in rows if r["warm_from"]]
    print()
    print("| timestamps | n | s each | MB each | held-out PSNR (dB) |")
    print("|---|---:|---:|---:|---:|")
    for label, group in (("keyframes (cold)", cold), ("warm-started", warm), ("all", rows)):
        print(
            f"| {label} | {len(group)} | {_mean([r['seconds'] for r in group])} | "
            f"{_mean([r['mb'] for r in group])} | {_mean([r['psnr_db'] for r in group])} |"
        )
    if cold and warm:
        ratio = np.mean([r["seconds"] for r in warm]) / np.mean([r["seconds"] for r in cold])
        print(f"\nwarm / cold seconds: {ratio:.3f} (1/{1 / ratio:.1f})")
        total_s = sum(r["seconds"] for r in rows)
        print(f"sum of timestamp seconds: {total_s:.0f} s; all cold would be about "
              f"{len(rows) * np.mean([r['seconds'] for r in cold]):.0f} s")  # fmt: skip
    by_pos: dict[int, list[float]] = {}
    for r in warm:
        by_pos.setdefault(r["chain_position"] // 10 * 10, []).append(r["psnr_db"])
    if by_pos:
        print("\nwarm PSNR by position in the chain: " + ", ".join(
            f"{p + 1}-{p + 10}: {np.mean(v):.2f} dB (n={len(v)})" for p, v in sorted(by_pos.items())
        ))  # fmt: skip
    if args.csv:
        with args.csv.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
