"""Compact storage of a warm-started case against a full PLY per timestamp.

A short sim case (intraoperative, people moving) is reconstructed as one warm chain: the first
timestamp cold, each later one from the one before as stored (as ``egosurg reconstruct
--warm-start`` does). Each timestamp is stored both ways; the stored form is decoded and
rendered into the held-out right cameras beside the in-memory model. It prints MB per
timestamp each way and the near-field PSNR of the in-memory and the decoded models.

    .venv/bin/python bench/bench_case_storage.py --sets 5 --steps 200 --warm-steps 25 --width 320
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import torch

from protocol.formats.rig_calibration import RigCalibration
from reconstructor.case import storage
from reconstructor.case.index import checksum_file
from reconstructor.case.warm import WarmStartConfig, seed_from_previous, warm_config
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.evaluation.metrics import psnr
from reconstructor.pipeline import reconstruct
from reconstructor.splats import ply
from reconstructor.splats.train import render
from sim.eval_set import EvalSetSpec, write_eval_set


def near_field_psnr(gaussians, views, raster) -> float:
    with torch.no_grad():
        return float(
            np.mean(
                [
                    psnr(
                        render(gaussians, v, raster, torch.zeros(3)).image.clamp(0, 1),
                        v.image,
                        v.mask,
                    )
                    for v in views
                ]
            )
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sets", type=int, default=5)
    ap.add_argument("--steps", type=int, default=200, help="cold steps of the keyframe")
    ap.add_argument("--warm-steps", type=int, default=25)
    ap.add_argument("--width", type=int, default=320, help="train_max_width_px")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_case_storage_"))
    spec = EvalSetSpec(
        seed=args.seed,
        phases=("intraoperative",),
        sets=args.sets,
        eval_sets=(0,),
        instants=1,
        view_size_px=(64, 40),
    )
    write_eval_set(root, spec)
    session = root / "intraoperative" / "session.h5"
    calibration = RigCalibration.read(root / "intraoperative" / "calibration.toml")
    base = ReconstructConfig(train_views="left", train_max_width_px=args.width)
    cold = dataclasses.replace(
        base,
        train=dataclasses.replace(base.train, warmup_steps=args.steps, refine_steps=0),
        auxiliary=dataclasses.replace(base.auxiliary, enabled=False),
    )
    wcfg = WarmStartConfig(steps=args.warm_steps, keyframe_every=args.sets)
    warm = warm_config(cold, wcfg)
    case = root / "case"
    rows = []
    parent: storage.Stored | None = None
    ref: dict = {}
    for k in range(args.sets):
        ts = load_timestamp(session, calibration, f"set:{k}")
        lineage: dict = {}
        if parent is None:
            result = reconstruct(ts, cold)
        else:
            previous = parent.gaussians()

            def init(ts_, fused, depths, previous=previous, lineage=lineage):
                seed = seed_from_previous(previous, ts_, fused, depths, wcfg, warm.init)
                lineage["alive"] = seed.alive
                return seed.gaussians

            result = reconstruct(ts, warm, init=init)
        name = f"t{k}"
        full = ply.write_ply(case / f"{name}.ply", result.gaussians, unit_quats=True)
        path = case / f"{name}{storage.SUFFIX}"
        storage.write_model(
            path,
            result.gaussians,
            parent=parent,
            parent_ref=ref or None,
            alive=lineage.get("alive"),
        )
        digest, size = checksum_file(path)
        ref = {"model": path.name, "xxh3_64": digest, "bytes": size}
        parent = storage.load_stored(case, path.name, digest, size)
        views, raster = result.held_out_views, result.config.raster
        rows.append(
            (
                k,
                result.gaussians.num,
                full.stat().st_size,
                size,
                near_field_psnr(result.gaussians, views, raster),
                near_field_psnr(parent.gaussians(), views, raster),
            )
        )
    print(
        f"\nsim seed {args.seed}, intraoperative, {args.sets} consecutive sets at 15 fps, one "
        f"warm chain, width {args.width}px, cold {args.steps} steps, warm {args.warm_steps}"
    )
    print("| set | gaussians | PLY MB | stored MB | PSNR in memory | PSNR stored | diff dB |")
    print("|---|---|---|---|---|---|---|")
    for k, n, pb, sb, pm, ps in rows:
        print(
            f"| {k} | {n} | {pb / 1e6:.2f} | {sb / 1e6:.2f} | {pm:.3f} | {ps:.3f} | "
            f"{ps - pm:+.4f} |"
        )
    ply_mb = np.mean([r[2] for r in rows]) / 1e6
    st_mb = np.mean([r[3] for r in rows]) / 1e6
    worst = max(abs(r[5] - r[4]) for r in rows)
    print(
        f"\nMB per timestamp: PLY {ply_mb:.2f}, stored {st_mb:.2f} ({ply_mb / st_mb:.1f}x); "
        f"largest PSNR difference {worst:.4f} dB"
    )


if __name__ == "__main__":
    main()
