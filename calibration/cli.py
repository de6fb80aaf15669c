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

A frame whose image fails its recorded checksum is skipped: left out of the background and
counted among the rejected frames as ``damaged image (checksum mismatch)``. A sealed session
is opened with ``--identity FILE`` (else ``EGOSURG_IDENTITY``), the identity of one of its
recipients.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import numpy as np

from calibration.detect.extract import ExtractConfig, extract
from calibration.observations import WandObservations
from calibration.report import exports
from calibration.report.page import write_report
from calibration.report.stats import ReportData
from calibration.report.thresholds import Thresholds
from calibration.report.verdict import annotate, verdict
from calibration.solve.config import SolveConfig
from calibration.solve.drift import Drift, align_to
from calibration.solve.solver import Solution, solve
from protocol.command import CommandArgumentError, command_parser
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.wand import WandSpec
from protocol.sealing import Identity
from protocol.sealing.arguments import add_identity_argument, identity_from_args

log = logging.getLogger(__name__)

DRIFT_LIMIT_DEG = 0.1
DRIFT_LIMIT_MM = 5.0


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
    parser = command_parser("egosurg calibrate", __doc__)
    parser.add_argument("session", help="a wand session recorded by 'egosurg record'")
    add_identity_argument(parser)
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
        raise CommandArgumentError("use either --refine or --check, not both")
    if not args.check and not args.out:
        raise CommandArgumentError("say where to write the calibration: --out calibration.toml")
    if not Path(args.session).exists():
        raise CommandArgumentError(f"{args.session} does not exist")
    wand = WandSpec.read(args.wand)
    old = RigCalibration.read(args.check or args.refine) if (args.check or args.refine) else None
    t0 = time.perf_counter()
    obs = _detect(args.session, wand, args.max_sets, identity_from_args(args))
    t_detect = time.perf_counter() - t0
    _print_detections(obs)
    solution = solve(obs, SolveConfig())
    t_solve = time.perf_counter() - t0 - t_detect
    thresholds = Thresholds(min_coverage_cells=args.min_coverage_cells, min_frames=args.min_frames)
    cal, data, drift = _calibration(obs, solution, wand, thresholds, old, args.session)
    passed, reasons = verdict(data, thresholds)
    _print_result(cal, passed, reasons, drift)
    if args.check:
        return _drift_check(drift, t0)
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


def _detect(
    session: str, wand: WandSpec, max_sets: int, identity: Identity | None
) -> WandObservations:
    """The wand in the session's frames, with a progress line on stderr."""

    def progress(k: int, n: int) -> None:
        print(f"\rdetecting the wand: {k}/{n} chunks", end="", file=sys.stderr, flush=True)

    cfg = ExtractConfig(max_sets=max_sets)
    obs = extract(session, wand, cfg, progress=progress, identity=identity)
    print(file=sys.stderr)
    return obs


def _print_detections(obs: WandObservations) -> None:
    used = obs.frames_used()
    for key in obs.sensors:
        rej = obs.rejected.get(key, {})
        print(
            f"{key.name}: wand in {used[key]} of {obs.frames_seen.get(key, 0)} frames"
            + (f"; rejected: {', '.join(f'{r} {n}' for r, n in rej.items())}" if rej else "")
        )


def _calibration(
    obs: WandObservations,
    solution: Solution,
    wand: WandSpec,
    thresholds: Thresholds,
    old: RigCalibration | None,
    session: str,
) -> tuple[RigCalibration, ReportData, Drift | None]:
    """The calibration with the report's quality and stats (in ``old``'s world frame when there
    is one), the report's data, and how far each sensor moved from ``old``."""
    used = obs.frames_used()
    frames = {
        key.name: (used[key], sum(obs.rejected.get(key, {}).values()), obs.rejected.get(key, {}))
        for key in obs.sensors
    }
    title = f"Calibration from {session}"
    data = report_data(solution, wand, frames, thresholds, title)
    cal = annotate(data, thresholds)
    cal = RigCalibration(
        sensors=cal.sensors,
        resolution=cal.resolution,
        world_frame=cal.world_frame,
        quality={**solution.calibration.quality, **cal.quality},
        metadata={**cal.metadata, "session": str(session)},
    )
    if old is None:
        return cal, data, None
    drift = align_to(cal, old, outlier_mm=DRIFT_LIMIT_MM)
    cal = drift.aligned
    solved = Solution(**{**solution.__dict__, "calibration": cal})
    return cal, report_data(solved, wand, frames, thresholds, title), drift


def _print_result(
    cal: RigCalibration, passed: bool, reasons: list[str], drift: Drift | None
) -> None:
    q = cal.quality
    print(
        f"reprojection error: mean {q['reprojection_px_mean']:.3f} px, p95 "
        f"{q['reprojection_px_p95']:.3f} px; wand length {q['wand_length_mm_mean']:.2f} +- "
        f"{q['wand_length_mm_sd']:.2f} mm, wand score {q['wand_score']:.3f} %"
    )
    print(f"verdict: {'PASS' if passed else 'FAIL'}")
    for r in reasons:
        print(f"  - {r}")
    if drift is None:
        return
    print(
        "camera drift against the old calibration (rotation deg, position mm), in the frame "
        "of SN" + ", SN".join(str(c) for c in drift.fitted_serials) + ":"
    )
    for s, rd, pm in zip(cal.sensors, drift.rotation_deg, drift.position_mm, strict=True):
        flag = "  MOVED" if rd > DRIFT_LIMIT_DEG or pm > DRIFT_LIMIT_MM else ""
        print(f"  {s.name:<20} {rd:8.4f} deg {pm:8.2f} mm{flag}")


def _drift_check(drift: Drift | None, t0: float) -> int:
    """``--check``'s answer: exit code 1 when a camera moved past the drift limits."""
    none = (np.zeros(1), np.zeros(1))
    rd, pm = (drift.rotation_deg, drift.position_mm) if drift is not None else none
    moved = bool((rd > DRIFT_LIMIT_DEG).any() or (pm > DRIFT_LIMIT_MM).any())
    print(
        f"drift check: {'RECALIBRATE: a camera moved' if moved else 'OK'} (limits "
        f"{DRIFT_LIMIT_DEG} deg, {DRIFT_LIMIT_MM} mm); took {time.perf_counter() - t0:.0f} s"
    )
    return 1 if moved else 0
