"""``egosurg reconstruct`` and ``egosurg render``.

Examples::

    egosurg reconstruct case.h5 --calibration calibration.toml --at 12.5 --out recon/
    egosurg reconstruct case.h5 --calibration calibration.toml --at set:120 --out recon/ \\
        --steps 300 --train-views left
    egosurg reconstruct case.h5 --at 12.5 --out recon/ --refiner difix \\
        --refiner-weights ~/weights/difix_ref
    egosurg reconstruct case.h5 --at 12.5 --out ablation/ --no-refinement
    egosurg reconstruct case.h5 --at 12.5 --out baseline/ --init random --no-refinement
    egosurg reconstruct case.h5 --every 1s --out case/ --workers 2     # a whole case
    egosurg render recon/t0012.500/splats.ply --camera SN41234567-left --out view.png
    egosurg render recon/t0012.500/splats.ply --camera "eye=2.0,-1.5,1.7 target=0,0,1" \\
        --hfov 80 --size 960x600 --out view.png

``--at`` is a time in seconds since the session started or ``set:N``. Each timestamp's outputs go
to ``OUT/t<seconds>/``: ``splats.ply`` (INRIA 3DGS layout), ``config.toml`` (the resolved
settings), ``log.txt``, ``summary.json``, ``points.ply``, the calibration used, and
``auxiliary_views.jpg`` (reference | render | refined for a few auxiliary views). A camera whose
image at the timestamp fails its recorded checksum is left out of it, like a camera missing from
the set: a warning names the camera, row and side, and ``summary.json`` lists it under
``damaged_images``.

Training is 500 warm-up steps on the input views, then 1500 steps on the input views plus 15
auxiliary views per input camera, rendered by the model after warm-up and corrected by the
refiner (``--refiner``: ``guided`` by default, no weights; ``difix`` with a local weights folder;
``none``; or a plug-in). The paper's ablations: ``--no-refinement`` ("EgoSurg without
diffusion") and ``--init random --no-refinement`` ("image-only 3DGS": Gaussians seeded at
random instead of from stereo depth); ``--evaluate`` adds the depth-reprojection baseline.

``--camera`` is a sensor name from the calibration saved beside the model (or ``--calibration``),
or ``"eye=X,Y,Z target=X,Y,Z"`` in metres in the calibration's world frame (z up, floor at 0),
with ``--hfov`` in degrees and ``--size WxH``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from protocol.camera import Camera, Intrinsics, Pose
from protocol.command import CommandArgumentError, command_parser, parse_size_px
from protocol.errors import UserError
from protocol.formats.rig_calibration import RigCalibration
from protocol.private_files import make_owner_only, plaintext_notice
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.data.views import EYE_NEAR_M
from reconstructor.raster.device import add_device_option, for_device
from reconstructor.splats.train import StepStats


def find_calibration(session: Path, given: str | None) -> tuple[RigCalibration, Path]:
    """The calibration to use: ``--calibration``, or ``calibration.toml`` beside the session."""
    if given:
        path = Path(given)
    else:
        path = session.parent / "calibration.toml"
        if not path.exists():
            raise CommandArgumentError(
                f"no calibration for {session}: pass --calibration FILE, or calibrate the rig "
                "first with 'egosurg calibrate WAND_SESSION.h5 --wand wand.toml --out "
                f"{path}'"
            )
    if not path.exists():
        raise CommandArgumentError(
            f"the calibration {path} does not exist; run 'egosurg calibrate' on a wand session "
            "recorded with this rig"
        )
    return RigCalibration.read(path), path


def _progress(stage: str, k: int, n: int, stats: StepStats) -> None:
    if k == 1 or k % 25 == 0 or k == n:
        print(
            f"\r{stage}: step {k}/{n}, loss {stats.loss:.4f}, {1000 * stats.seconds:.0f} ms/step",
            end="" if k < n else "\n",
            file=sys.stderr,
            flush=True,
        )


def reconstruct_parser() -> argparse.ArgumentParser:
    parser = command_parser("egosurg reconstruct", __doc__)
    parser.add_argument("session", help="a session recorded by 'egosurg record'")
    add_identity_argument(parser)
    parser.add_argument("--calibration", help="calibration.toml (default: beside the session)")
    parser.add_argument("--at", action="append", help="time in s, or set:N (repeatable)")
    case = parser.add_argument_group("a whole case (docs/case.md)")
    case.add_argument("--every", help="one timestamp per this interval: 1s, 0.5s, 500ms")
    case.add_argument("--from", dest="from_s", type=float, help="first time, s (default: start)")
    case.add_argument("--to", dest="to_s", type=float, help="last time, s (default: end)")
    case.add_argument("--workers", type=int, default=1, help="processes, one timestamp each")
    case.add_argument("--ray", metavar="auto|ADDRESS", help="run the timestamps as Ray tasks")
    start = case.add_mutually_exclusive_group()
    start.add_argument(
        "--warm-start",
        action="store_true",
        help="start each timestamp from the one before it (the default; EVALUATION.md, Table 3B)",
    )
    start.add_argument(
        "--cold", action="store_true", help="train every timestamp from scratch instead"
    )
    case.add_argument("--warm-steps", type=int, help="training steps of a warm timestamp (250)")
    case.add_argument("--keyframe-every", type=int, help="a cold timestamp every N (10)")
    case.add_argument("--force", action="store_true", help="redo a case made with other settings")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument(
        "--depth-cache",
        metavar="DIR",
        help="keep each timestamp's stereo depth and fused cloud here and reuse them (a rerun "
        "with other training settings, or a machine without OpenCV contrib or open3d)",
    )
    parser.add_argument("--config", help="a config TOML with settings to change")
    add_device_option(parser, "the config's [raster] backend, the CPU's numba kernels")
    parser.add_argument("--steps", type=int, help="total training steps (default 2000)")
    parser.add_argument("--train-views", choices=("all", "left"), help="'left': near-field test")
    parser.add_argument("--stereo-matcher", help="'sgbm' (default) or an installed plug-in")
    parser.add_argument("--stereo-weights", help="local weights path for a learned matcher")
    parser.add_argument(
        "--refiner", metavar="NAME", help="auxiliary-view refiner: guided (default), difix, none"
    )
    parser.add_argument(
        "--refiner-weights", metavar="PATH", help="local weights of the refiner (difix: a folder)"
    )
    parser.add_argument(
        "--no-refinement",
        action="store_true",
        help="no auxiliary views: the ablation 'EgoSurg without diffusion'",
    )
    parser.add_argument(
        "--init",
        choices=("depth", "random"),
        help="Gaussians from stereo depth (default) or random ('image-only 3DGS' baseline)",
    )
    parser.add_argument(
        "--evaluate",
        action="store_true",
        help="score the views against the recorded images and the depth-reprojection baseline",
    )
    return parser


def main_reconstruct(argv: list[str]) -> int:
    args = reconstruct_parser().parse_args(argv)

    session = Path(args.session)
    if not session.exists():
        raise CommandArgumentError(f"the session {session} does not exist")
    calibration, cal_path = find_calibration(session, args.calibration)
    config = ReconstructConfig.read(args.config) if args.config else ReconstructConfig()
    config = _with_options(config, args)
    config = dataclasses.replace(config, raster=for_device(config.raster, args.device))
    if bool(args.at) == bool(args.every):
        raise CommandArgumentError(
            "give --at TIME (single timestamps) or --every INTERVAL (a whole case), not both"
            if args.at
            else "give --at TIME for single timestamps or --every INTERVAL for a whole case"
        )
    if args.cold and (args.warm_steps or args.keyframe_every):
        raise CommandArgumentError(
            "--warm-steps and --keyframe-every set up warm start, which --cold turns off: "
            "drop one or the other"
        )
    from reconstructor.depth.cache import DepthCache

    # a folder that cannot be used fails now, in one line, before any work
    depth_cache = DepthCache(Path(args.depth_cache)) if args.depth_cache else None
    identity = identity_from_args(args)  # a damaged file fails now, before any work
    if args.every:
        from reconstructor.case.cli import reconstruct_case

        return reconstruct_case(args, session, cal_path, config, identity)
    out = Path(args.out)
    for at in args.at:
        from reconstructor.pipeline import reconstruct

        ts = load_timestamp(
            session, calibration, at, calibration_source=str(cal_path), identity=identity
        )
        if ts.missing_serials:
            print(
                f"set {ts.set_index}: camera(s) "
                f"{', '.join(f'SN{s}' for s in ts.missing_serials)} missing; reconstructing "
                f"from the other {len(ts.camera_serials)}",
                file=sys.stderr,
            )
        for image in ts.damaged_images:  # the camera was left out of this timestamp
            print(
                f"set {ts.set_index}: {image} image is damaged (checksum mismatch); "
                "reconstructing without that camera",
                file=sys.stderr,
            )
        run_dir = out / f"t{ts.t_s:09.3f}"
        t0 = time.perf_counter()
        result = reconstruct(
            ts,
            config,
            run_dir,
            calibration=calibration,
            progress=_progress,
            depth_cache=depth_cache,
        )
        print(
            f"{run_dir / 'splats.ply'}: {result.gaussians.num} Gaussians, set {ts.set_index} "
            f"(t = {ts.t_s:.3f} s), {time.perf_counter() - t0:.0f} s"
        )
        if args.evaluate:
            from reconstructor.evaluation.held_out import evaluate

            evaluate(result, run_dir)
            print((run_dir / "eval.md").read_text())
        if ts.sealing is not None:  # a sealed session's model, written plain where asked
            print(plaintext_notice("model and points (splats.ply, points.ply)", run_dir),
                  file=sys.stderr)  # fmt: skip
    return 0


def _with_options(config: ReconstructConfig, args: argparse.Namespace) -> ReconstructConfig:
    changes: dict[str, object] = {}
    if args.steps is not None:
        if args.steps < 1:
            raise CommandArgumentError(f"--steps must be at least 1, got {args.steps}")
        warm = min(config.train.warmup_steps, args.steps)
        changes["train"] = dataclasses.replace(
            config.train, warmup_steps=warm, refine_steps=args.steps - warm
        )
    if args.train_views:
        changes["train_views"] = args.train_views
    if args.stereo_matcher:
        changes["stereo_matcher"] = args.stereo_matcher
    if args.stereo_weights:
        changes["stereo_weights"] = args.stereo_weights
    if args.init:
        changes["init_method"] = args.init
    aux: dict[str, object] = {}
    if args.no_refinement:
        if args.refiner or args.refiner_weights:
            raise CommandArgumentError(
                "--no-refinement turns the auxiliary views off; drop --refiner/--refiner-weights "
                "or --no-refinement"
            )
        aux["enabled"] = False
    if args.refiner:
        aux["refiner"] = args.refiner
    if args.refiner_weights:
        aux["refiner_weights"] = args.refiner_weights
    if aux:
        changes["auxiliary"] = dataclasses.replace(config.auxiliary, **aux)  # type: ignore[arg-type]
    return dataclasses.replace(config, **changes) if changes else config  # type: ignore[arg-type]


# ---- render ----------------------------------------------------------------------------------


def parse_camera(
    spec: str, calibration: RigCalibration | None, hfov_deg: float, size: tuple[int, int]
) -> Camera:
    """A sensor name from the calibration, or ``eye=X,Y,Z target=X,Y,Z``."""
    text = spec.strip()
    if text.startswith("eye="):
        parts = dict(p.split("=", 1) for p in text.split() if "=" in p)
        try:
            eye = np.array([float(v) for v in parts["eye"].split(",")])
            target = np.array([float(v) for v in parts["target"].split(",")])
            if eye.shape != (3,) or target.shape != (3,):
                raise ValueError
            pose = Pose.look_at(eye, target)
        except (KeyError, ValueError):
            raise CommandArgumentError(
                f'--camera {spec!r}: write it as "eye=X,Y,Z target=X,Y,Z" (metres)'
            ) from None
        intr = Intrinsics.from_fov(size[0], size[1], hfov_deg)
        return Camera(name="virtual", intrinsics=intr, pose=pose)
    if calibration is None:
        raise CommandArgumentError(
            f"--camera {spec!r} names a sensor, but no calibration was found beside the model; "
            'pass --calibration FILE or give "eye=X,Y,Z target=X,Y,Z"'
        )
    for s in calibration.sensors:
        if s.name == text:
            return Camera(name=s.name, intrinsics=s.intrinsics.undistorted(), pose=s.pose)
    names = ", ".join(s.name for s in calibration.sensors)
    raise CommandArgumentError(f"--camera {spec!r} is not a sensor of the calibration: {names}")


def render_camera(
    model_path: Path,
    camera: Camera,
    background=(0.0, 0.0, 0.0),
    near_m: float = 0.0,
    device: str = "cpu",
) -> np.ndarray:
    """(H, W, 3) uint8 RGB of the splat model seen by ``camera`` (pinhole), leaving out what is
    nearer than ``near_m`` or the model's near plane; rendered on ``device``."""
    from reconstructor.data.views import novel_view
    from reconstructor.splats import ply
    from reconstructor.splats.train import render

    g = ply.read_ply(model_path)
    raster = for_device(_raster_config(model_path), device)
    if near_m > raster.near_m:
        raster = dataclasses.replace(raster, near_m=near_m)
    with torch.no_grad():
        out = render(g, novel_view(camera), raster, torch.tensor(background))
    return (out.image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def _raster_config(model_path: Path):
    cfg_path = model_path.parent / "config.toml"
    if cfg_path.exists():
        try:
            return ReconstructConfig.read(cfg_path).raster
        except UserError:
            pass
    return ReconstructConfig().raster


def main_render(argv: list[str]) -> int:
    parser = command_parser("egosurg render", __doc__)
    parser.add_argument("model", help="a splat PLY written by 'egosurg reconstruct'")
    parser.add_argument("--camera", required=True, help='sensor name or "eye=.. target=.."')
    parser.add_argument("--out", required=True, help="PNG to write")
    parser.add_argument("--calibration", help="calibration.toml (default: beside the model)")
    parser.add_argument("--hfov", type=float, default=90.0, help="virtual camera hfov, degrees")
    parser.add_argument("--size", default="960x600", help="virtual camera size WxH")
    parser.add_argument(
        "--near-m",
        type=float,
        default=0.0,
        help="leave out what is nearer to the camera than this, metres (default: the model's "
        f"near plane); from a person's eye use {EYE_NEAR_M:g}, which leaves out their own head",
    )
    add_device_option(parser)
    args = parser.parse_args(argv)
    model = Path(args.model)
    if not model.exists():
        raise CommandArgumentError(f"the model {model} does not exist")
    cal_path = Path(args.calibration) if args.calibration else model.parent / "calibration.toml"
    calibration = RigCalibration.read(cal_path) if cal_path.exists() else None
    if not 1.0 < args.hfov < 179.0:
        raise CommandArgumentError(f"--hfov {args.hfov}: must be between 1 and 179 degrees")
    if not (math.isfinite(args.near_m) and 0.0 <= args.near_m < 10.0):
        raise CommandArgumentError(
            f"--near-m {args.near_m}: give a distance in metres from 0 to 10 (0.2 from an eye)"
        )
    size_px = parse_size_px(args.size, "--size", min_px=8, max_px=None)
    camera = parse_camera(args.camera, calibration, args.hfov, size_px)
    t0 = time.perf_counter()
    rgb = render_camera(model, camera, near_m=args.near_m, device=args.device or "cpu")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), rgb[:, :, ::-1]):
        raise CommandArgumentError(f"cannot write {out}; use a .png or .jpg path")
    make_owner_only(out)  # a picture from an earlier run kept its mode when rewritten
    print(f"{out}: {camera.name} {rgb.shape[1]}x{rgb.shape[0]}, {time.perf_counter() - t0:.2f} s")
    print(plaintext_notice("render", out), file=sys.stderr)
    return 0
