"""``egosurg sim roles``: each person's true eye over time, as a roles file, and the site's true
boxes, so that replay and line of sight can be judged against the simulator's exact truth.
Given a session, both files record it (their ``[session]`` table): the review commands refuse
them for another session's case.

Case time (seconds since the session started) maps to sim time through the session's start:
``t_sim = (started_unix_ns - SIM_EPOCH_UNIX_NS) / 1e9 + t_case``; ``egosurg sim eval-set``
sessions start at the sim epoch, so there the two are equal. A sim rig's recording (``egosurg
sim demo``, ``sim.deploy``) says in its case metadata that its sim time 0 is the rig's own epoch
and that it loops its prerendered content (``SimRigFiles.sim_metadata``): its roles are the eyes
of the moment each picture shows (``SessionClock.sim_time_s``).

Examples::

    egosurg sim roles evalset/intraoperative/session.h5 --out roles.toml --site-out site.toml
    egosurg sim roles take.h5 --identity reader-keys/site.identity --out roles.toml

A sealed session's seed and phase are in its sealed metadata: ``--identity FILE`` (or
``$EGOSURG_IDENTITY``) opens them, or give ``--seed`` and ``--phase``.
    egosurg sim roles --seed 3 --phase intraoperative --from 2 --to 4 --every 0.1 --out roles.toml
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from protocol.command import CommandArgumentError, add_subcommand
from protocol.formats.session_id import SessionId
from protocol.formats.site import SiteBox, site_toml, surface_points
from protocol.formats.trajectory import Keyframe, Trajectory, write_trajectories
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from sim.phases import PHASES
from sim.timing import read_session_clock
from sim.world import World

log = logging.getLogger(__name__)

# Screens a reviewer asks about, by the sim's object name -> the site box's name stem.
_SCREENS = {"monitor_screen": "monitor", "anaesthesia_screen": "anaesthesia-screen"}


def role_trajectories(
    world: World,
    case_times_s: np.ndarray,
    *,
    sim_offset_s: float = 0.0,
    fov_deg: float = 90.0,
    sim_time: Callable[[float], float] | None = None,
) -> list[Trajectory]:
    """One trajectory per person: their egocentric eye (``World.head_poses``) at each time.
    The sim time of case time ``t`` is ``sim_time(t)`` (a session's clock,
    ``SessionClock.sim_time_s``: a sim rig loops its content) or ``t + sim_offset_s``."""
    keys: dict[str, list[Keyframe]] = {}
    for t in case_times_s:
        t_sim = sim_time(float(t)) if sim_time is not None else float(t) + sim_offset_s
        for name, pose in world.head_poses(t_sim).items():
            keys.setdefault(name, []).append(Keyframe.from_pose(float(t), pose, fov_deg))
    return [Trajectory(name=n, keyframes=tuple(k)) for n, k in keys.items()]


def site_boxes(world: World) -> list[SiteBox]:
    """The room's screens as boxes (their +x face is the screen), named ``monitor-a``, ..."""
    out: list[SiteBox] = []
    counts: dict[str, int] = {}
    for obj in world.static_objects:
        stem = _SCREENS.get(obj.name)
        if stem is None:
            continue
        v = np.asarray(obj.mesh.vertices, np.float64)
        # sim.geometry.box orders corners 4*ix + 2*iy + iz: its axes are corner differences
        x, y, z = v[4] - v[0], v[2] - v[0], v[1] - v[0]
        k = counts[stem] = counts.get(stem, 0) + 1
        name = f"{stem}-{'abcdefgh'[k - 1]}" if stem == "monitor" else stem
        out.append(
            SiteBox(
                name=name,
                centre_m=tuple(float(c) for c in v.mean(axis=0)),  # type: ignore[arg-type]
                size_m=(
                    float(np.linalg.norm(x)),
                    float(np.linalg.norm(y)),
                    float(np.linalg.norm(z)),
                ),
                yaw_deg=float(np.degrees(np.arctan2(x[1], x[0]))),
                front_only=True,
            )
        )
    return out


def true_visible_fraction(
    world: World,
    t_sim_s: float,
    eye_m: np.ndarray,
    box: SiteBox,
    per_face: int = 12,
    near_m: float = 0.3,
) -> float:
    """The fraction of ``box``'s points facing ``eye_m`` that a ray from the eye reaches
    unobstructed in the true scene at ``t_sim_s`` (0 when no counted face faces the eye).

    Rays start ``near_m`` from the eye, past the viewer's own head (the question is whether they
    could see it by turning; reconstructor's sightline leaves out what lies that near, its
    HEAD_CLEARANCE_M). The back of a head (cap) lies up to 0.25 m behind the eye: rays that
    started at 0.2 m began inside it and hit its far side, so a screen behind a viewer counted
    their own skull as the blocker."""
    pts = surface_points(box, eye_m, per_face)
    if len(pts) == 0:
        return 0.0
    eye = np.asarray(eye_m, np.float64)
    d = pts - eye
    dist = np.linalg.norm(d, axis=1)
    unit = d / dist[:, None]
    rays = np.concatenate([eye + near_m * unit, unit], axis=1)
    t_hit, _, _ = world.scene_at(t_sim_s).cast_rays(rays.astype(np.float32))
    # the sampled point lies on the box's own surface: a hit within 1 cm of it is the box
    return float(np.mean(t_hit >= dist - near_m - 0.01))


def _times(args: argparse.Namespace, first_s: float, last_s: float) -> np.ndarray:
    t0 = first_s if args.t_from is None else args.t_from
    t1 = last_s if args.t_to is None else args.t_to
    if not (args.every > 0 and np.isfinite(args.every)):
        raise CommandArgumentError(f"--every {args.every}: give a positive number of seconds")
    if not (np.isfinite(t0) and np.isfinite(t1) and 0 <= t0 <= t1):
        raise CommandArgumentError(f"--from {t0} --to {t1}: need 0 <= from <= to (seconds)")
    n = int(np.floor((t1 - t0) / args.every + 1e-9)) + 1
    return t0 + args.every * np.arange(n)


def cmd_roles(args: argparse.Namespace) -> int:
    offset_s, seed, phase = 0.0, args.seed, args.phase
    sim_time: Callable[[float], float] | None = None  # a session's clock, where one is given
    session: SessionId | None = None  # without a session file: none to record
    first_s = last_s = float("nan")
    if args.session:
        path = Path(args.session)
        clock = read_session_clock(path, identity_from_args(args))
        meta, set_s = clock.case_metadata, clock.set_times_s
        if len(set_s) == 0:
            raise CommandArgumentError(f"the session {path} holds no synchronised sets")
        # a live rig's first set can be stamped a fraction of a millisecond before the
        # session's start: the keyframes then start at 0
        first_s, last_s = max(float(set_s[0]), 0.0), float(set_s[-1])
        offset_s, session, sim_time = clock.sim_offset_s, clock.session, clock.sim_time_s
        if seed is None:
            if "seed" not in meta:
                raise clock.metadata_needed(path, "sim seed", "--seed and --phase")
            seed = int(meta["seed"])
        phase = phase or meta.get("phase")
        if phase is None:
            raise clock.metadata_needed(path, "sim phase", "--phase")
        if clock.sealed_for:
            log.warning(
                "%s is sealed and read without an identity: the world is --seed %s --phase %s "
                "on an eval-set session's clock, without the session's scripted drape contact, "
                "if it had one, and without a sim rig's looping content, if it came from one "
                "(pass --identity)",
                path,
                seed,
                phase,
            )
    elif args.t_from is None or args.t_to is None:
        raise CommandArgumentError("without a session, give --from and --to (seconds)")
    if phase not in PHASES:
        raise CommandArgumentError(f"--phase {phase!r}: choose one of {', '.join(PHASES)}")
    contact = bool(args.session) and meta.get("contact") == "1"  # sim/contact.py
    world = World.from_seed(0 if seed is None else int(seed), phase=phase, contact=contact)
    times = _times(args, first_s, last_s)
    if times[0] + offset_s < 0:
        raise CommandArgumentError(f"--from {times[0]} lies before the simulation starts")
    roles = role_trajectories(
        world, times, sim_offset_s=offset_s, fov_deg=args.fov, sim_time=sim_time
    )
    if not roles:
        raise CommandArgumentError(f"the {phase} phase has no people: no roles to write")
    write_trajectories(args.out, roles, session)
    print(f"{args.out}: {len(roles)} roles ({', '.join(r.name for r in roles)}), "
          f"{len(times)} keyframes each, {times[0]:.3f} s to {times[-1]:.3f} s")  # fmt: skip
    if args.site_out:
        boxes = site_boxes(world)
        Path(args.site_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.site_out).write_text(site_toml(boxes, session))
        print(f"{args.site_out}: {len(boxes)} boxes ({', '.join(b.name for b in boxes)})")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``egosurg sim roles`` on the ``egosurg sim`` subparsers."""
    p = add_subcommand(
        sub, "roles", "each person's true eye over time (a roles file) and boxes", cmd_roles
    )
    p.add_argument("session", nargs="?", help="a sim session (eval-set); its seed, phase, times")
    p.add_argument("--seed", type=int, default=None, help="world seed (default: the session's)")
    p.add_argument("--phase", default=None, help="phase (default: the session's)")
    p.add_argument("--from", dest="t_from", type=float, help="first case time, s")
    p.add_argument("--to", dest="t_to", type=float, help="last case time, s")
    p.add_argument("--every", type=float, default=0.1, help="keyframe interval, s (0.1)")
    p.add_argument("--fov", type=float, default=90.0, help="horizontal field of view, degrees")
    p.add_argument("--out", required=True, help="roles TOML to write")
    p.add_argument("--site-out", help="also write the room's screens as a site file")
    add_identity_argument(p)
