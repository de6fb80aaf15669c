"""``egosurg people``: who stood where and looked where, from the recording (docs/replay.md).

Examples::

    egosurg people CASE/ --out CASE/people.toml
    egosurg people session.h5 --every 0.5 --out people.toml --identity me.identity
    egosurg people CASE/ --out CASE/people.toml --background empty_room.h5
    egosurg people name CASE/people.toml --list --suggest
    egosurg people name CASE/people.toml track3=surgeon track1=anaesthetist \\
        --out CASE/roles.toml
    egosurg replay CASE/ --role surgeon --roles CASE/roles.toml --out surgeon.mp4

The first finds the people in each timestamp of a case (its session's stereo at the case's
timestamps; the fused points the case keeps when the session is gone) or of a session (stereo at
every ``--every`` seconds), tracks them and writes one trajectory per track
(``track1``, ``track2``, ...) with each keyframe's confidence and the gaps where the track was
hidden. ``name`` turns tracks into roles: the file the review tools' ``--roles`` reads.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from protocol.command import CommandArgumentError, command_parser
from protocol.formats.trajectory import read_trajectory_file
from protocol.sealing.arguments import add_identity_argument, identity_from_args

log = logging.getLogger(__name__)


def _progress(stage: str, k: int, n: int) -> None:
    if k == n or k % 10 == 0:
        print(f"  {stage}: {k}/{n} timestamps", file=sys.stderr, flush=True)


def main(argv: list[str]) -> int:
    if argv and argv[0] == "name":
        return main_name(argv[1:])
    p = command_parser("egosurg people", __doc__)
    p.add_argument("source", help="a case folder or a session .h5")
    p.add_argument("--out", required=True, help="the people file to write (TOML)")
    p.add_argument("--every", type=float, default=0.5, help="a session's interval, s (0.5)")
    p.add_argument("--from", dest="t_from", type=float, help="first time, s")
    p.add_argument("--to", dest="t_to", type=float, help="last time, s")
    p.add_argument("--calibration", help="a session's calibration (default: beside it)")
    p.add_argument("--background", help="a recording (case or session) of the empty room")
    add_identity_argument(p)
    args = p.parse_args(argv)
    if not (args.every > 0 and args.every < 3600):
        raise CommandArgumentError(f"--every {args.every}: give a positive number of seconds")
    from reconstructor.people.config import PeopleConfig
    from reconstructor.people.output import write_people
    from reconstructor.people.run import find_people
    from reconstructor.people.sources import open_source

    identity = identity_from_args(args)
    config = PeopleConfig()
    if logging.getLogger().getEffectiveLevel() > logging.DEBUG:
        # stereo's per-camera lines, four per timestamp, would bury the progress lines
        logging.getLogger("reconstructor.pipeline").setLevel(logging.WARNING)
    source = open_source(
        args.source,
        identity=identity,
        every_s=args.every,
        calibration=args.calibration,
        t_from_s=args.t_from,
        t_to_s=args.t_to,
    )
    background = (
        open_source(args.background, identity=identity, every_s=1.0) if args.background else None
    )
    print(f"{source.path}: {len(source.times_s)} timestamps ({source.kind})", file=sys.stderr)
    t0 = time.perf_counter()
    people = find_people(source, config, background=background, progress=_progress)
    wall = time.perf_counter() - t0
    n = len(source.times_s)
    if not people.tracks:
        # an empty people file is no trajectory file the review tools could read: write none
        print(
            f"{source.path}: nobody found in {n} timestamps ({wall / n:.2f} s per timestamp); "
            f"{args.out} not written. If people were in the room, check --from/--to and, where "
            "someone stood still for most of the span, give --background EMPTY_ROOM (a recording "
            "of the empty room)",
            file=sys.stderr,
        )
        return 1
    out = write_people(args.out, people, config, source.session)
    print(
        f"{out}: {len(people.tracks)} tracks over {n} timestamps ({wall / n:.2f} s per "
        f"timestamp; background from {people.background_from})"
    )
    file = read_trajectory_file(out)
    from reconstructor.replay.names import describe

    for tr in file.trajectories:
        print("  " + describe(tr))
    print(f"name them: egosurg people name {out} track1=ROLE ... --out roles.toml")
    return 0


def main_name(argv: list[str]) -> int:
    p = command_parser("egosurg people name", __doc__)
    p.add_argument("people", help="the people file 'egosurg people' wrote")
    p.add_argument("names", nargs="*", help="TRACK=ROLE, e.g. track3=surgeon")
    p.add_argument("--out", help="the roles file to write (for the review tools' --roles)")
    p.add_argument(
        "--list", action="store_true", help="list the tracks (and the roles an --out file names)"
    )
    p.add_argument("--suggest", action="store_true", help="print suggestions from the room")
    args = p.parse_args(argv)
    from reconstructor.replay.names import (
        describe,
        names_in,
        parse_names,
        role_lines,
        suggest,
        write_roles,
    )

    file = read_trajectory_file(args.people)
    if args.list:
        for tr in file.trajectories:
            print(describe(tr))
        if not args.names and args.out and Path(args.out).is_file():  # the names given so far
            roles_file = read_trajectory_file(args.out).trajectories
            given = names_in(roles_file, file.trajectories, args.out)
            print("\n".join([f"{args.out}:", *role_lines(given, file.trajectories)]))
    if args.suggest:
        for line in suggest(file.trajectories):
            print(line)
    if not args.names:
        if args.list or args.suggest:
            return 0
        raise CommandArgumentError("name at least one track (e.g. track3=surgeon), or --list")
    if not args.out:
        raise CommandArgumentError("give --out roles.toml, the roles file to write")
    names = parse_names(args.names)
    roles = write_roles(args.out, file, names)
    print(f"{args.out}: {len(roles)} roles ({', '.join(r.name for r in roles)})")
    for line in role_lines(names, file.trajectories):  # which tracks each role joins
        print("  " + line)
    return 0
