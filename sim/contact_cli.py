"""``egosurg sim contact``: the drape's field box and the true contact intervals of a sim
session made with ``egosurg sim eval-set --contact`` (the script is in ``sim/contact.py``).

Example::

    egosurg sim contact es/intraoperative/session.h5 --field-out field.toml --truth-out truth.csv
    egosurg sim contact take.h5 --identity site.identity --field-out f.toml --truth-out t.csv

The seed, phase and contact script are the session's metadata: a sealed session's opens with
``--identity FILE`` (or ``$EGOSURG_IDENTITY``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from protocol.command import CommandArgumentError, add_subcommand
from protocol.formats.site import site_toml
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from sim.contact import DRAPE_FIELD
from sim.contact_truth import true_field_intervals, write_truth_csv


def cmd_contact(args: argparse.Namespace) -> int:
    from sim.timing import read_session_clock
    from sim.world import World

    path = Path(args.session)
    clock = read_session_clock(path, identity_from_args(args))
    meta, set_s = clock.case_metadata, clock.set_times_s
    if clock.sealed_for:
        raise clock.metadata_needed(path, "sim seed, phase and contact script")
    if meta.get("contact") != "1" or "seed" not in meta or "phase" not in meta:
        raise CommandArgumentError(
            f"{path} is not a sim session with the scripted contact; make one with "
            "'egosurg sim eval-set --contact --phases intraoperative ...'"
        )
    if len(set_s) == 0:
        raise CommandArgumentError(f"the session {path} holds no synchronised sets")
    world = World.from_seed(int(meta["seed"]), phase=meta["phase"], contact=True)
    offset_s, t0, t1 = clock.sim_offset_s, set_s[0], set_s[-1]
    rows = true_field_intervals(world, DRAPE_FIELD, t0 + offset_s, t1 + offset_s)
    rows = [(n, a - offset_s, b - offset_s) for n, a, b in rows]  # back to case time
    Path(args.field_out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.field_out).write_text(site_toml([DRAPE_FIELD], clock.session))
    write_truth_csv(Path(args.truth_out), rows)
    print(f"{args.field_out}: the field box {DRAPE_FIELD.name!r}; {args.truth_out}: "
          f"{len(rows)} true intervals in the field, {t0:.3f}-{t1:.3f} s")  # fmt: skip
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``egosurg sim contact`` on the ``egosurg sim`` subparsers."""
    p = add_subcommand(
        sub, "contact", "the drape's field box and the true contact intervals", cmd_contact
    )
    p.add_argument("session", help="a sim session made with 'egosurg sim eval-set --contact'")
    p.add_argument("--field-out", required=True, help="the field box as a site file (TOML)")
    p.add_argument("--truth-out", required=True, help="CSV of true in-field intervals")
    add_identity_argument(p)
