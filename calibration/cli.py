"""``egosurg calibrate``: extrinsic calibration of the rig from a recorded wand session.

Examples::

    egosurg calibrate wand_session.h5 --wand wand.toml --out calibration.toml
    egosurg calibrate short_wand.h5 --wand wand.toml --refine calibration.toml --out new.toml
    egosurg calibrate short_wand.h5 --wand wand.toml --check calibration.toml

It detects the three spheres in every sensor's frames, labels them, solves the four cameras'
poses (intrinsics and each ZED X's internal stereo pose come from the factory files in the
session) and writes the calibration TOML, a report (``report.html`` and pictures) and exports
(OpenCV YAML, COLMAP text, nerfstudio ``transforms.json``) next to it.

``--refine OLD`` solves the new session and expresses the result in OLD's world frame, so that
everything already reconstructed with OLD stays in place; it prints how far each camera moved.
``--check OLD`` measures how far OLD has drifted from what a new wand session says, without
writing a calibration; it exits with code 1 when a camera moved past the drift limits.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from calibration import exports
from calibration.drift import align_to
from calibration.extract import ExtractConfig, extract
from calibration.report import ReportData, Thresholds, annotate, verdict
from calibration.report_page import write_report
from calibration.solve import Solution, SolveConfig, solve
from protocol.errors import UserError
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.wand import WandSpec

log = logging.getLogger(__name__)

DRIFT_LIMIT_DEG = 0.1
DRIFT_LIMIT_MM = 5.0


class CalibrateArgumentError(UserError, ValueError):
    pass


def report_data(
    solution: Solution, wand: WandSpec, obs_frames: dict, thresholds: Thresholds, title: str
) -> ReportData:
    r = solution.residuals
    return ReportData(
        calibration=solution.calibration,
        sensor_names=tuple(k.name for k in r.sensors),
        obs_sensor=r.sensor_index,
        obs_px=r.pixel_px,
        obs_residual_px=np.nan_to_num(r.residual_px, nan=0.0),
        obs_inlier=r.inlier & np.isfinite(r.residual_px).all(axis=1),
        obs_set=r.set_index,
        wand_length_mm=solution.wand_lengths_mm,
        wand_spec_length_mm=wand.distances_mm[2],
        frames=obs_frames,
        wand_trajectory_m=solution.trajectory_m,
        thresholds=thresholds,
        title=title,
    )


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="egosurg calibrate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("session", help="a wand session recorded by 'egosurg record'")
    parser.add_argument(
        "--wand", required=True, help="wand.toml (egosurg sim wand-file writes one)"
    )
    parser.add_argument("--out", help="calibration.toml to write (not with --check)")
    parser.add_argument(
        "--report-dir",
        help="where report.html and exports go (default: next to --out, in <name>_report/)",
    )
    parser.add_argument("--refine", metavar="OLD", help="keep OLD's world frame; show changes")
    parser.add_argument("--check", metavar="OLD", help="report OLD's drift; write nothing")
    parser.add_argument(
        "--max-sets",
        type=int,
        default=ExtractConfig().max_sets,
        help="synchronised sets to use, spread over the session (default %(default)s; more "
        "costs time for little accuracy, see BENCHMARKS.md 'Wand calibration')",
    )
    parser.add_argument(
        "--min-coverage-cells",
        type=int,
        default=Thresholds().min_coverage_cells,
        help="pass/fail: image cells of a 4x4 grid the wand must cover",
    )
    parser.add_argument(
        "--min-frames",
        type=int,
        default=Thresholds().min_frames,
        help="pass/fail: frames with the wand per sensor",
    )
    args = parser.parse_args(argv)
    if args.check and args.refine:
        raise CalibrateArgumentError("use either --refine or --check, not both")
    if not args.check and not args.out:
        raise CalibrateArgumentError("say where to write the calibration: --out calibration.toml")
    if not Path(args.session).exists():
        raise CalibrateArgumentError(f"{args.session} does not exist")
    wand = WandSpec.read(args.wand)
    old = RigCalibration.read(args.check or args.refine) if (args.check or args.refine) else None
    t0 = time.perf_counter()

    def progress(k: int, n: int) -> None:
        print(f"\rdetecting the wand: {k}/{n} chunks", end="", file=sys.stderr, flush=True)

    obs = extract(args.session, wand, ExtractConfig(max_sets=args.max_sets), progress=progress)
    print(file=sys.stderr)
    t_detect = time.perf_counter() - t0
    used = obs.frames_used()
    for key in obs.sensors:
        rej = obs.rejected.get(key, {})
        print(
            f"{key.name}: wand in {used[key]} of {obs.frames_seen.get(key, 0)} frames"
            + (f"; rejected: {', '.join(f'{r} {n}' for r, n in rej.items())}" if rej else "")
        )
    solution = solve(obs, SolveConfig())
    t_solve = time.perf_counter() - t0 - t_detect
    thresholds = Thresholds(min_coverage_cells=args.min_coverage_cells, min_frames=args.min_frames)
    frames = {
        key.name: (used[key], sum(obs.rejected.get(key, {}).values()), obs.rejected.get(key, {}))
        for key in obs.sensors
    }
    data = report_data(solution, wand, frames, thresholds, f"Calibration from {args.session}")
    cal = annotate(data, thresholds)
    cal = RigCalibration(
        sensors=cal.sensors,
        resolution=cal.resolution,
        world_frame=cal.world_frame,
        quality={**solution.calibration.quality, **cal.quality},
        metadata={**cal.metadata, "session": str(args.session)},
    )
    drift = None
    if old is not None:
        moved_rig = align_to(cal, old, outlier_mm=DRIFT_LIMIT_MM)
        cal = moved_rig.aligned
        drift = (moved_rig.rotation_deg, moved_rig.position_mm)
        data = report_data(
            Solution(**{**solution.__dict__, "calibration": cal}),
            wand,
            frames,
            thresholds,
            f"Calibration from {args.session}",
        )
    passed, reasons = verdict(data, thresholds)
    q = cal.quality
    print(
        f"reprojection error: mean {q['reprojection_px_mean']:.3f} px, p95 "
        f"{q['reprojection_px_p95']:.3f} px; wand length {q['wand_length_mm_mean']:.2f} +- "
        f"{q['wand_length_mm_sd']:.2f} mm, wand score {q['wand_score']:.3f} %"
    )
    print(f"verdict: {'PASS' if passed else 'FAIL'}")
    for r in reasons:
        print(f"  - {r}")
    if drift is not None:
        print(
            "camera drift against the old calibration (rotation deg, position mm), in the frame "
            "of SN" + ", SN".join(str(c) for c in moved_rig.fitted_serials) + ":"
        )
        for s, rd, pm in zip(cal.sensors, *drift, strict=True):
            flag = "  MOVED" if rd > DRIFT_LIMIT_DEG or pm > DRIFT_LIMIT_MM else ""
            print(f"  {s.name:<20} {rd:8.4f} deg {pm:8.2f} mm{flag}")
    if args.check:
        rd, pm = drift if drift is not None else (np.zeros(1), np.zeros(1))
        moved = bool((rd > DRIFT_LIMIT_DEG).any() or (pm > DRIFT_LIMIT_MM).any())
        print(
            f"drift check: {'RECALIBRATE: a camera moved' if moved else 'OK'} (limits "
            f"{DRIFT_LIMIT_DEG} deg, {DRIFT_LIMIT_MM} mm); took {time.perf_counter() - t0:.0f} s"
        )
        return 1 if moved else 0
    out = Path(args.out)
    cal.write(out)
    report_dir = Path(args.report_dir) if args.report_dir else out.with_name(out.stem + "_report")
    html = write_report(data, report_dir, thresholds)
    exports.export_opencv_yaml(cal, report_dir / "calibration_opencv.yaml")
    exports.export_colmap(cal, report_dir / "colmap")
    exports.export_nerfstudio(cal, report_dir / "transforms.json")
    t_total = time.perf_counter() - t0
    print(
        f"timings: detection {t_detect:.1f} s ({obs.frames_decoded} images), solve "
        f"{t_solve:.1f} s, report {t_total - t_detect - t_solve:.1f} s, total {t_total:.1f} s"
    )
    print(
        f"wrote {out}, the report {html} and exports in {report_dir} "
        f"({time.perf_counter() - t0:.0f} s)"
    )
    return 0
