"""``egosurg sim``: the simulated operating room from the command line.

Examples::

    egosurg sim info --phase intraoperative --t 2.0
    egosurg sim frames --out frames/ --t-start 0 --t-end 0.5 --resolution SVGA
    egosurg sim factory --out factory/
    egosurg sim wand-file --out wand.toml
    egosurg sim view --out ego.png --t 3.0 --person surgeon
    egosurg sim view --out side.png --t 3.0 --eye 3,0,1.7 --look-at 0,0,1 --depth-out side_depth.png
    egosurg sim pictures --out pictures/
    egosurg sim eval-set --out evalset/ --seed 3 --phases empty,intraoperative --sets 10
"""

from __future__ import annotations

import argparse
import csv
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Intrinsics, Pose, Resolution
from protocol.command import (
    CommandArgumentError,
    add_subcommand,
    command_parser,
    parse_size_px,
)
from sim.phases import PHASES

log = logging.getLogger(__name__)


def _vector(text: str, what: str) -> np.ndarray:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise CommandArgumentError(
            f"{what} {text!r} must be three numbers like 1.5,0,1.7"
        ) from None
    if len(vals) != 3:
        raise CommandArgumentError(f"{what} {text!r} must have three comma-separated numbers")
    return np.asarray(vals)


def _world_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--phase", default="intraoperative", choices=PHASES, help="workflow phase")


def _world(args: argparse.Namespace):
    from sim.world import World

    if args.seed < 0:
        raise CommandArgumentError(f"--seed {args.seed} must be >= 0")
    return World.from_seed(args.seed, phase=args.phase)


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")


def _write_depth_mm(path: Path, depth_m: np.ndarray) -> None:
    """16-bit PNG in millimetres; 0 where nothing was hit."""
    mm = np.where(np.isfinite(depth_m), np.round(depth_m * 1000.0), 0)
    if not cv2.imwrite(str(path), np.clip(mm, 0, 65535).astype(np.uint16)):
        raise OSError(f"could not write {path}")


def cmd_info(args: argparse.Namespace) -> int:
    world = _world(args)
    print(f"simulated OR: seed {args.seed}, phase {args.phase}, t = {args.t:g} s")
    for u in world.rig:
        c = u.left_pose.centre_m
        st = u.factory.stereo(Resolution.HD1200)
        print(
            f"  camera {u.index}: SN{u.serial} on {u.node_id}, left sensor at "
            f"({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) m, fx {st.left.fx_px:.1f} px, "
            f"baseline {st.baseline_m * 1000:.1f} mm"
        )
    for p in world.people(args.t):
        h = p.head_centre_m
        print(f"  {p.name} ({p.role}): head at ({h[0]:.2f}, {h[1]:.2f}, {h[2]:.2f}) m")
    wand = world.wand_centres(args.t)
    if wand is not None:
        print(
            "  wand sphere centres (m): "
            + "; ".join(f"({x:.3f}, {y:.3f}, {z:.3f})" for x, y, z in wand)
        )
    return 0


def cmd_frames(args: argparse.Namespace) -> int:
    """Write each camera's frames in a time range, following its free-running clock."""
    world = _world(args)
    res = Resolution.parse(args.resolution)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    world.write_factory_files(out)
    units = [world.unit(int(c)) for c in args.cameras.split(",")] if args.cameras else world.rig
    rows = []
    plan = [(u, world.clock(u).frames(args.t_start, args.t_end)) for u in units]
    total = sum(int((~truth.dropped).sum()) for _, truth in plan)
    done = 0
    for unit, truth in plan:
        for i, t, stamp, dropped in zip(
            truth.frame_index, truth.exposure_t_s, truth.capture_unix_ns, truth.dropped, strict=True
        ):
            rows.append((unit.serial, int(i), f"{t:.9f}", int(stamp), int(dropped)))
            if dropped:
                continue
            for r in world.render_stereo(unit, float(t), res):
                side = "left" if r.camera.name.endswith("left") else "right"
                base = out / f"SN{unit.serial}" / f"{side}_{int(i):06d}"
                _write_rgb(base.with_suffix(".png"), r.image_rgb)
                if args.depth:
                    _write_depth_mm(base.with_name(base.name + "_depth_mm.png"), r.depth_m)
            done += 1
            print(f"\rrendered {done}/{total} stereo frames", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    with open(out / "truth.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["camera_serial", "frame_index", "exposure_t_s", "capture_unix_ns", "dropped"])
        w.writerows(rows)
    print(
        f"wrote {done} stereo frames of {len(units)} cameras to {out}/ (ground truth in "
        f"{out / 'truth.csv'}, factory files SN*.conf)"
    )
    return 0


def cmd_factory(args: argparse.Namespace) -> int:
    world = _world(args)
    for path in world.write_factory_files(args.out):
        print(path)
    return 0


def cmd_wand_file(args: argparse.Namespace) -> int:
    from protocol.formats.wand import WandSpec

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(WandSpec().to_toml())
    print(out)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    world = _world(args)
    w, h = parse_size_px(args.size, "--size")
    if args.person:
        heads = world.head_poses(args.t)
        if args.person not in heads:
            names = ", ".join(sorted(heads)) or "nobody (this phase has no people)"
            raise CommandArgumentError(f"no person {args.person!r} at t={args.t}; present: {names}")
        pose = heads[args.person]
    elif args.eye is not None and args.look_at is not None:
        pose = Pose.look_at(_vector(args.eye, "--eye"), _vector(args.look_at, "--look-at"))
    else:
        raise CommandArgumentError("say where the camera is: --person NAME, or --eye and --look-at")
    intr = Intrinsics.from_fov(w, h, args.hfov)
    cam = world.virtual_camera(pose, intr, name=args.person or "virtual")
    r = world.render(cam, args.t)
    _write_rgb(Path(args.out), r.image_rgb)
    print(args.out)
    if args.depth_out:
        _write_depth_mm(Path(args.depth_out), r.depth_m)
        print(args.depth_out)
    return 0


def cmd_pictures(args: argparse.Namespace) -> int:
    from sim import pictures

    world = _world(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path in write_pictures(world, out, args.t, args.video_s, pictures):
        print(path)
    return 0


def write_pictures(world, out: Path, t_s: float, video_s: float, pictures) -> list[Path]:
    mosaic = out / "rig_views.png"
    _write_rgb(mosaic, pictures.rig_mosaic(world, t_s))
    topdown = pictures.topdown_map(world, t_s, out / "room_topdown.png")

    def progress(k: int, n: int) -> None:
        print(f"\rground-truth video: frame {k}/{n}", end="", file=sys.stderr, flush=True)

    video = pictures.ground_truth_video(
        world, out / "ground_truth.mp4", t_s, t_s + video_s, progress=progress
    )
    print(file=sys.stderr)
    return [mosaic, topdown, video]


def cmd_eval_set(args: argparse.Namespace) -> int:
    from sim.eval_set import EvalSetSpec, write_eval_set

    try:
        spec = EvalSetSpec(
            seed=args.seed,
            phases=tuple(p.strip() for p in args.phases.split(",") if p.strip()),
            resolution=args.resolution,
            fps=args.fps,
            t_start_s=args.t_start,
            sets=args.sets,
            eval_sets=tuple(int(k) for k in args.eval_sets.split(",") if k.strip()),
            jpeg_quality=args.jpeg_quality,
            view_size_px=parse_size_px(args.view_size, "--view-size"),
            view_hfov_deg=args.view_hfov,
            contact=args.contact,
            instants=args.instants,
            instant_every_s=args.instant_every,
            near_field_instants=args.near_field_instants,
        )
    except ValueError as exc:
        print(f"egosurg sim eval-set: {exc}", file=sys.stderr)
        return 2
    eval_set = write_eval_set(Path(args.out), spec)
    views = sum(len(s.views) for s in eval_set.scenes)
    print(
        f"wrote {Path(args.out) / 'eval_set.toml'}: {len(eval_set.scenes)} scenes, "
        f"{spec.sets} sets and {spec.instants} instant(s) per phase, {views} egocentric "
        "reference views"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser("egosurg sim", __doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = add_subcommand(sub, "info", "print the rig, the people and the wand at a time", cmd_info)
    _world_args(p)
    p.add_argument("--t", type=float, default=0.0, help="sim time in seconds")

    p = add_subcommand(sub, "frames", "write the rig's frames for a time range to PNG", cmd_frames)
    _world_args(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--t-start", type=float, default=0.0, help="seconds (default 0)")
    p.add_argument("--t-end", type=float, default=0.2, help="seconds (default 0.2)")
    p.add_argument("--resolution", default="SVGA", help="HD1200, HD1080 or SVGA (default SVGA)")
    p.add_argument("--cameras", default="", help="camera indices, e.g. 0,2 (default: all four)")
    p.add_argument("--depth", action="store_true", help="also write true depth (16-bit PNG, mm)")

    p = add_subcommand(sub, "factory", "write each camera's SN<serial>.conf", cmd_factory)
    _world_args(p)
    p.add_argument("--out", required=True, help="output folder")

    p = add_subcommand(sub, "wand-file", "write the simulated wand's wand.toml", cmd_wand_file)
    p.add_argument("--out", required=True, help="output file, e.g. wand.toml")

    p = add_subcommand(sub, "view", "render a virtual pinhole camera (ground truth)", cmd_view)
    _world_args(p)
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--t", type=float, required=True, help="sim time in seconds")
    p.add_argument("--person", help="use this person's egocentric head pose")
    p.add_argument("--eye", help="camera position x,y,z in metres")
    p.add_argument("--look-at", help="point to look at x,y,z in metres")
    p.add_argument("--hfov", type=float, default=90.0, help="horizontal field of view, degrees")
    p.add_argument("--size", default="960x600", help="image size WxH (default 960x600)")
    p.add_argument("--depth-out", help="also write true depth here (16-bit PNG, mm)")

    p = add_subcommand(
        sub, "pictures", "rig views, top-down map and a ground-truth video", cmd_pictures
    )
    _world_args(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--t", type=float, default=4.0, help="sim time of the pictures")
    p.add_argument("--video-s", type=float, default=3.0, help="video length in seconds")

    p = add_subcommand(
        sub,
        "eval-set",
        "scenes of each workflow phase plus egocentric truth, for evaluation",
        cmd_eval_set,
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=3, help="world seed (default 3)")
    p.add_argument(
        "--phases", default="empty,setup,intraoperative,turnover", help="comma-separated phases"
    )
    p.add_argument("--resolution", default="SVGA", help="HD1200, HD1080 or SVGA (default SVGA)")
    p.add_argument("--fps", type=float, default=15.0, help="set rate (default 15)")
    p.add_argument("--t-start", type=float, default=2.0, help="sim time of the first set")
    p.add_argument("--sets", type=int, default=10, help="consecutive sets per phase (default 10)")
    p.add_argument("--eval-sets", default="0", help="sets with egocentric truth, e.g. 0,9")
    p.add_argument("--jpeg-quality", type=int, default=90, help="as the agents encode (90)")
    p.add_argument("--view-size", default="960x600", help="egocentric view size WxH")
    p.add_argument("--view-hfov", type=float, default=90.0, help="egocentric hfov, degrees")
    p.add_argument(
        "--instants",
        type=int,
        default=5,
        help="instants per phase with every person's view: set 0 and later ones (default 5)",
    )
    p.add_argument(
        "--instant-every", type=float, default=8.0, help="seconds between instants (default 8)"
    )
    p.add_argument(
        "--near-field-instants",
        type=int,
        default=3,
        help="the first instants that are near-field instants too (default 3)",
    )
    p.add_argument("--contact", action="store_true", help="script a drape contact (sim/contact.py)")

    from sim.roles import add_parser as add_roles_parser  # egosurg sim roles

    add_roles_parser(sub)
    from sim.contact_cli import add_parser as add_contact_parser  # egosurg sim contact

    add_contact_parser(sub)
    return parser


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args))
