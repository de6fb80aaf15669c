"""``egosurg replay`` and ``egosurg sightline``: review a reconstructed case (docs/replay.md).

Examples::

    egosurg replay case/ --role surgeon --roles roles.toml --out surgeon.mp4 --pip
    egosurg replay case/ --trajectory walk.toml --out walk.mp4 --fps 15 --size 960x600
    egosurg replay case/ --role surgeon --roles roles.toml --out grid.mp4 --layout grid
    egosurg sightline case/ --viewer anaesthetist --roles roles.toml --target monitor-a \\
        --site site.toml --offset "1m left-posterior" --out los/
    egosurg sterile case/ --field field.toml --roles roles.toml \\
        --sterile-roles surgeon,assistant,nurse_scrub --out sterile/
"""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from protocol.command import CommandArgumentError, command_parser, parse_size_px
from protocol.errors import UserError
from protocol.formats.trajectory import Trajectory, read_trajectories
from protocol.private_files import make_owner_only, plaintext_notice
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from reconstructor.case.sealing import is_sealed_case
from reconstructor.data.views import EYE_NEAR_M
from reconstructor.raster.device import add_device_option, check_device

if TYPE_CHECKING:
    from reconstructor.replay.session_check import CaseInputs

log = logging.getLogger(__name__)


def pick_trajectory(
    trajectory: str | None, role: str | None, roles: str | None, inputs: CaseInputs | None = None
) -> Trajectory:
    """The path asked for: ``--trajectory FILE`` (its only one, or ``--role`` in it), or
    ``--role NAME --roles FILE``; with ``inputs``, the file must be made for its case's session
    (``reconstructor/replay/session_check.py``)."""
    source = trajectory or roles
    if source is None:
        raise CommandArgumentError(
            "say whose view: --trajectory FILE, or --role NAME with --roles roles.toml "
            "(egosurg sim roles writes one)"
        )
    if trajectory and roles:
        raise CommandArgumentError("give --trajectory or --roles, not both")
    found = read_trajectories(source) if inputs is None else inputs.trajectories(source)
    if role is None:
        if len(found) == 1:
            return found[0]
        raise CommandArgumentError(
            f"{source} holds {len(found)} trajectories; pick one with --role: "
            + ", ".join(t.name for t in found)
        )
    for t in found:
        if t.name == role:
            return t
    raise CommandArgumentError(
        f"no role {role!r} in {source}; it has: {', '.join(t.name for t in found)}"
    )


def _progress(unit: str):
    from tqdm import tqdm

    bar = None

    def update(k: int, n: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=n, unit=unit, leave=False)
        bar.update(k - bar.n)
        if k >= n:
            bar.close()

    return update


def add_timezone_argument(parser) -> None:
    parser.add_argument(
        "--timezone",
        help="the zone the time of day is shown in, an IANA name (Europe/Berlin) or UTC "
        "(default: this machine's)",
    )


def main_replay(argv: list[str]) -> int:
    from reconstructor.replay.clock import pick_zone
    from reconstructor.replay.path import CameraPath
    from reconstructor.replay.run import ReplayConfig, replay
    from reconstructor.replay.session_check import CaseInputs
    from reconstructor.replay.video import seconds_span

    p = command_parser("egosurg replay", __doc__)
    p.add_argument("case", help="a case folder (egosurg reconstruct --every ... --out CASE/)")
    p.add_argument("--trajectory", help="a trajectory TOML (docs/replay.md)")
    p.add_argument("--role", help="a role's name in --roles (or in --trajectory)")
    p.add_argument("--roles", help="a roles TOML (egosurg sim roles writes the sim's)")
    p.add_argument("--out", required=True, help="the MP4 to write")
    p.add_argument("--fps", type=float, default=10.0, help="frames per second of case time (10)")
    p.add_argument("--size", default="960x600", help="WxH, even (960x600)")
    p.add_argument("--from", dest="t_from", type=float, help="first case time, s")
    p.add_argument("--to", dest="t_to", type=float, help="last case time, s")
    p.add_argument(
        "--pip",
        action="store_true",
        help="inset the nearest real camera's frame (a damaged one shows DAMAGED and is listed)",
    )
    p.add_argument(
        "--layout",
        choices=("render", "grid"),
        default="render",
        help="grid: the render beside a 2x2 grid of the real cameras nearest the path, "
        "the video twice --size's width (render)",
    )
    add_timezone_argument(p)
    add_identity_argument(p)  # --pip and --layout grid read the case's session
    p.add_argument("--no-preload", action="store_true", help="read each model when first shown")
    p.add_argument("--allow-gaps", action="store_true", help="show the model before a gap")
    p.add_argument("--near-m", type=float, help=f"near plane, m ({EYE_NEAR_M:g} for a role)")
    p.add_argument(
        "--observed", action="store_true", help="also OUT.observed.mp4 and .csv (docs/replay.md)"
    )
    add_device_option(p)
    args = p.parse_args(argv)
    check_device(args.device)
    folder = Path(args.case)
    traj = pick_trajectory(args.trajectory, args.role, args.roles, CaseInputs(folder))
    near = args.near_m if args.near_m is not None else (EYE_NEAR_M if args.roles else 0.0)
    if not (math.isfinite(near) and 0 <= near < 10):
        raise CommandArgumentError(f"--near-m {near}: give 0 to 10 metres")
    try:
        config = ReplayConfig(
            fps=args.fps, size_px=parse_size_px(args.size, "--size", even=True),
            t_from_s=args.t_from, t_to_s=args.t_to, preload=not args.no_preload, near_m=near,
            pip=args.pip, allow_gaps=args.allow_gaps, observed=args.observed,
            device=args.device or "cpu", layout=args.layout, timezone=args.timezone,
        )  # fmt: skip
    except ValueError as exc:
        if isinstance(exc, UserError):
            raise
        raise CommandArgumentError(str(exc)) from None
    pick_zone(args.timezone)  # a wrong name: one line before any work
    out = Path(args.out)
    if out.suffix.lower() != ".mp4":
        raise CommandArgumentError(f"--out {out}: give a .mp4 path")
    # only the real cameras (--pip, the grid) read the session
    identity = identity_from_args(
        args, needed=args.pip or args.layout == "grid" or is_sealed_case(folder)
    )  # the real cameras (--pip, the grid) read the session; a sealed case's models need it
    stats = replay(
        folder, CameraPath(traj), out, config, progress=_progress("frame"), identity=identity
    )
    span = seconds_span(stats.t_from_s, stats.t_to_s)
    print(
        f"{out}: {stats.frames} frames, {span} of case time, {stats.models} models; "
        f"{stats.fps:.1f} frames/s rendered, "
        f"{stats.load_wait_s:.2f} s waiting on models (preload {'on' if config.preload else 'off'})"
    )
    if stats.stale_frames:
        print(
            f"warning: {stats.stale_frames} of {stats.frames} frames show a model older than the "
            f"case's spacing ({stats.spacing_s:.3f} s), marked STALE in the video",
            file=sys.stderr,
        )
    if stats.gap_frames:  # a card, not a view: nobody followed the role there
        print(
            f"{stats.gap_frames} of {stats.frames} frames fall in the path's gaps (seen by no "
            "camera, or between two tracks): shown as NOT FOLLOWED cards, no view",
            file=sys.stderr,
        )
    if stats.damaged_images:  # shown as "DAMAGED" in the inset, never as the changed image
        print(
            f"warning: --pip: {len(stats.damaged_images)} damaged real frame(s) not shown "
            f"(checksum mismatch): {', '.join(stats.damaged_images)}",
            file=sys.stderr,
        )
    written = [out]
    if config.observed:
        from reconstructor.replay.observed_case import observed_paths

        print("observed versus inferred: {} and {}".format(*observed_paths(out)))
        written.extend(observed_paths(out))
    for path in written:
        make_owner_only(path)  # a video from an earlier run kept its mode when rewritten
    print(plaintext_notice("video", ", ".join(map(str, written))), file=sys.stderr)
    return 0


def main_sightline(argv: list[str]) -> int:
    from reconstructor.replay.clock import pick_zone
    from reconstructor.replay.path import CameraPath
    from reconstructor.replay.session_check import CaseInputs
    from reconstructor.replay.sightline import parse_offset
    from reconstructor.replay.sightline_run import VISIBLE_ENOUGH, obstruction_words, sightline

    p = command_parser("egosurg sightline", __doc__)
    p.add_argument("case", help="a case folder")
    p.add_argument("--viewer", required=True, help="a role in --roles (or a --trajectory)")
    p.add_argument("--roles", help="a roles TOML (egosurg sim roles writes the sim's)")
    p.add_argument("--trajectory", help="or a trajectory TOML")
    p.add_argument("--target", required=True, help="a box's name in --site")
    p.add_argument("--site", required=True, help="the site file naming the boxes")
    p.add_argument("--offset", help='a counterfactual position, e.g. "1m left-posterior"')
    p.add_argument(
        "--out", required=True, help="folder: sightline.csv, timeline.png, plan_*.png, worst_*.png"
    )
    add_identity_argument(p)  # a sealed session's case
    add_timezone_argument(p)
    add_device_option(p)
    args = p.parse_args(argv)
    check_device(args.device)
    pick_zone(args.timezone)  # a wrong name: one line before any work
    inputs = CaseInputs(Path(args.case))
    traj = pick_trajectory(args.trajectory, args.viewer, args.roles, inputs)
    # the other people, for who blocks the line (the file was checked just above)
    others = tuple(CameraPath(t) for t in read_trajectories(args.roles)) if args.roles else ()
    boxes = inputs.boxes(args.site)
    if args.target not in boxes:
        raise CommandArgumentError(
            f"no target {args.target!r} in {args.site}; it has: {', '.join(boxes)}"
        )
    offset = parse_offset(args.offset) if args.offset else None
    out = Path(args.out)
    rows = sightline(
        Path(args.case), CameraPath(traj), boxes[args.target], offset, out,
        progress=_progress("timestamp"), device=args.device or "cpu",
        identity=identity_from_args(args, needed=is_sealed_case(Path(args.case))),
        others=others, site_boxes=tuple(boxes.values()), timezone=args.timezone,
    )  # fmt: skip
    for label in dict.fromkeys(r.position for r in rows):
        sel = [r.visible_fraction for r in rows if r.position == label]
        blocked = sum(f < VISIBLE_ENOUGH for f in sel)
        inferred = sum(r.rests_on_inferred for r in rows if r.position == label)
        print(f"{args.viewer} {label}: {args.target} visible {min(sel):.2f}-{max(sel):.2f}, "
              f"less than half visible at {blocked} of {len(sel)} timestamps; the answer "
              f"rests on inferred content at {inferred}")  # fmt: skip
        print(f"{args.viewer} {label}: {obstruction_words(rows, label)}")
    print(f"wrote {out / 'sightline.csv'}, {out / 'timeline.png'}, a plan of each answer "
          "(plan_*.png) and the worst instants' views (worst_*.png)")  # fmt: skip
    print(plaintext_notice("renders of the case (worst_*.png)", out), file=sys.stderr)
    return 0


def main_sterile(argv: list[str]) -> int:
    """``egosurg sterile CASE/ --field field.toml --out sterile/`` (docs/replay.md)."""
    from reconstructor.replay.clock import pick_zone
    from reconstructor.replay.session_check import CaseInputs
    from reconstructor.replay.sterile import SterileConfig
    from reconstructor.replay.sterile_run import read_roles, sterile
    from reconstructor.replay.video import seconds_span

    p = command_parser("egosurg sterile", __doc__)
    p.add_argument("case", help="a case folder")
    p.add_argument("--field", required=True, help="a site file with the field box(es)")
    p.add_argument("--box", help="one box of --field (default: every box in it)")
    p.add_argument("--roles", help="a roles TOML: each event's nearest role")
    p.add_argument("--sterile-roles", default="", help="roles whose entries are allowed, a,b")
    p.add_argument("--out", required=True,
                   help="folder: events.csv, timeline.png, event_*.png, event_*_camera.png, "
                   "event_*_clip.mp4")  # fmt: skip
    p.add_argument("--from", dest="t_from", type=float, help="first case time, s")
    p.add_argument("--to", dest="t_to", type=float, help="last case time, s")
    p.add_argument("--min-points", "--min-gaussians", dest="min_points", type=int, default=8,
                   help="moving points of one person in the field for a contact, each one 2 cm "
                   "cell stereo saw (8)")  # fmt: skip
    p.add_argument("--min-timestamps", type=int, default=1, help="an event's shortest run (1)")
    p.add_argument("--static-fraction", type=float, default=0.5,
                   help="occupied this often: static scene (0.5)")  # fmt: skip
    p.add_argument("--margin-sigmas", type=float, default=SterileConfig.margin_sigmas,
                   help="a point counts in the box only this many depth uncertainties inside "
                   f"it (0: on its faces counts; {SterileConfig.margin_sigmas:g})")  # fmt: skip
    p.add_argument("--disparity-noise-px", type=float,
                   default=SterileConfig.disparity_noise_px,
                   help="the stereo matcher's disparity noise, pixels "
                   f"({SterileConfig.disparity_noise_px:g})")  # fmt: skip
    p.add_argument("--min-air-share", type=float, default=SterileConfig.min_air_share,
                   help="share of a contact's points in the box that must lie where a camera "
                   "saw through at other times (0: off; "
                   f"{SterileConfig.min_air_share:g})")  # fmt: skip
    p.add_argument("--min-cameras", type=int, default=SterileConfig.min_cameras,
                   help="cameras that must have seen a contact's points in the box (1: off; "
                   f"{SterileConfig.min_cameras})")  # fmt: skip
    p.add_argument("--max-filled-before", type=float, default=SterileConfig.max_filled_before,
                   help="where a contact crosses into the box, the share of the 0.5-2 s before at "
                   "which it was filled, at most, at one of its timestamps (1: off; "
                   f"{SterileConfig.max_filled_before:g})")  # fmt: skip
    p.add_argument("--allow-gaps", action="store_true", help="skip pending or failed timestamps")
    add_identity_argument(p)  # a sealed session's case
    add_timezone_argument(p)
    add_device_option(p)
    args = p.parse_args(argv)
    check_device(args.device)
    pick_zone(args.timezone)  # a wrong name: one line before any work
    inputs = CaseInputs(Path(args.case))
    boxes = inputs.boxes(args.field)
    if args.box is not None:
        if args.box not in boxes:
            raise CommandArgumentError(
                f"no box {args.box!r} in {args.field}; it has: {', '.join(boxes)}"
            )
        boxes = {args.box: boxes[args.box]}
    sterile_roles = tuple(r.strip() for r in args.sterile_roles.split(",") if r.strip())
    try:
        config = SterileConfig(
            min_points=args.min_points, static_fraction=args.static_fraction,
            min_timestamps=args.min_timestamps, margin_sigmas=args.margin_sigmas,
            disparity_noise_px=args.disparity_noise_px, sterile_roles=sterile_roles,
            min_air_share=args.min_air_share, min_cameras=args.min_cameras,
            max_filled_before=args.max_filled_before,
        )  # fmt: skip
    except ValueError as exc:
        raise CommandArgumentError(str(exc)) from None
    paths = read_roles(args.roles, sterile_roles, inputs)
    out = Path(args.out)
    result = sterile(
        Path(args.case), list(boxes.values()), paths, out, config, t_from_s=args.t_from,
        t_to_s=args.t_to, allow_gaps=args.allow_gaps, progress=_progress("timestamp"),
        device=args.device or "cpu",
        identity=identity_from_args(args, needed=is_sealed_case(Path(args.case))),
        timezone=args.timezone,
    )  # fmt: skip
    for k, ev in enumerate(result.events, 1):
        kind = "sterile role" if ev.sterile_role else "CONTACT"
        print(f"{k}: {kind} {ev.role or '?'} in {ev.field} {seconds_span(ev.start_s, ev.end_s)}")
    print(f"{len(result.contacts)} contact events ({len(result.events) - len(result.contacts)} "
          f"of sterile roles); wrote {out / 'events.csv'}, {out / 'timeline.png'}")  # fmt: skip
    if result.set_aside:
        spans = "; ".join(f"{ev.role or '?'} {seconds_span(ev.start_s, ev.end_s)}"
                          for ev in result.set_aside)  # fmt: skip
        print(
            f"{len(result.set_aside)} candidate contact(s) set aside: where they cross into the "
            f"box was filled the seconds before (someone standing at its face: stereo smear "
            f"off their body, or their reach after standing there): {spans}; listed in "
            f"{out / 'set_aside.csv'}; --max-filled-before 1 reports them as contacts"
        )
    if result.real_note:
        print(result.real_note, file=sys.stderr)
    for path in result.files(out):
        make_owner_only(path)  # a file from an earlier run kept its mode when rewritten
    what = "renders of the case (event_*.png)"
    if result.cameras:
        what += " and real camera stills and clips (event_*_camera.png, event_*_clip.mp4)"
    print(plaintext_notice(what, out), file=sys.stderr)
    if result.evidence == "gaussians":
        print("judged on the models' Gaussian centres: this case was stored without its fused "
              "points (made before 2026-11-27, or PLY models); rerun its reconstruct command in "
              "a new folder for the points the tool is measured on (docs/replay.md)")  # fmt: skip
    return 0


def main_view(argv: list[str]) -> int:
    """``egosurg view CASE/ [--roles roles.toml] [--site site.toml] [--field field.toml]``."""
    from reconstructor.replay.session_check import CaseInputs
    from reconstructor.replay.view import CaseViewer, ViewConfig

    p = command_parser(
        "egosurg view",
        "Browse a case in a web browser (docs/replay.md, Viewer). Example:\n\n"
        "    egosurg view case/ --roles roles.toml --site site.toml --field field.toml\n"
        "    egosurg view case/ --people case/people.toml --roles case/roles.toml",
    )
    p.add_argument("case", help="a case folder")
    p.add_argument("--roles", help="a roles TOML: role cameras to look through")
    p.add_argument(
        "--people", help="a people file (egosurg people): name its tracks; names go to --roles"
    )
    p.add_argument("--site", action="append", default=[], help="target boxes (repeatable)")
    p.add_argument("--field", action="append", default=[], help="field boxes (repeatable)")
    p.add_argument("--port", type=int, default=8080, help="HTTP port (8080; 0: any free)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (127.0.0.1: this machine)")
    p.add_argument("--save-to", default="viewpoints.toml", help="'Save viewpoint' adds here")
    p.add_argument("--name", default="viewer", help="the trajectory saved viewpoints go in")
    p.add_argument("--camera-from", help="a trajectory TOML: the page opens at its first keyframe")
    add_identity_argument(p)  # a sealed session's case
    add_timezone_argument(p)
    args = p.parse_args(argv)
    inputs = CaseInputs(Path(args.case))  # --camera-from too: a start from another session
    start = inputs.trajectories(args.camera_from)[0].keyframes[0] if args.camera_from else None
    config = ViewConfig(
        host=args.host, port=args.port, roles=Path(args.roles) if args.roles else None,
        people=Path(args.people) if args.people else None,
        sites=tuple(map(Path, args.site)), fields=tuple(map(Path, args.field)),
        save_to=Path(args.save_to), viewpoint_name=args.name, start=start,
        timezone=args.timezone,
    )  # fmt: skip
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        log.warning(
            "serving on %s: other machines can reach it; only a page with the printed URL's "
            "token gets the case",
            args.host,
        )
    identity = identity_from_args(args, needed=is_sealed_case(Path(args.case)))
    viewer = CaseViewer(Path(args.case), config, identity)
    print(f"egosurg view: {args.case} at {viewer.url} (Ctrl-C to stop)", flush=True)
    signal.signal(signal.SIGINT, _stop_on_signal)
    signal.signal(signal.SIGTERM, _stop_on_signal)
    try:
        viewer.wait()
    except KeyboardInterrupt:
        pass
    finally:
        _exit_soon(10.0)  # before the close, which is what can hang
        viewer.close()
    # and leave at once: a library's threads or native teardown at interpreter exit (where the
    # timer's thread no longer runs) must not keep a stopped viewer alive; nothing is pending
    # (a saved viewpoint is written when it is saved)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _stop_on_signal(signum: int, frame: object) -> None:
    """Ctrl-C (or a service manager's SIGTERM): the process ends within 10 s whatever a
    library thread or the close does, then the close runs as after Ctrl-C."""
    _exit_soon(10.0)
    raise KeyboardInterrupt


def _exit_soon(seconds: float) -> None:
    """Ctrl-C stops the viewer: should a library thread (viser's server, a model read in flight)
    not end within ``seconds`` of the close, the process leaves without it (exit code 0). Nothing
    is lost: a saved viewpoint is written to its file when it is saved."""
    timer = threading.Timer(seconds, os._exit, args=(0,))
    timer.daemon = True
    timer.start()
