"""``egosurg report``: one self-contained HTML report of a reconstructed case (docs/report.md).

Examples::

    egosurg report case/ --out case-report.html
    egosurg report case/ --roles roles.toml --sterile sterile/ --sightline los/ \\
        --times 2.0,2.1 --timezone Europe/Berlin --out case-report.html

It reads the case, its session (health, time of day, the real cameras' frames) and what
``egosurg sterile`` and ``egosurg sightline`` wrote for the case (their ``--out`` folders). A
section whose input is not given says "not run" with the command that makes it. A sealed
session is read with ``--identity FILE`` (or ``$EGOSURG_IDENTITY``); without one the report of
a case stored in plaintext is still made, without the real camera frames and the case metadata,
and says so at its top (a case whose models are sealed is refused in one line: docs/report.md).
"""

from __future__ import annotations

import datetime as dt
import logging
import shlex
import sys
from pathlib import Path

from protocol.command import CommandArgumentError, command_parser
from protocol.private_files import make_owner_only
from protocol.sealing.arguments import add_identity_argument, identity_from_args

log = logging.getLogger(__name__)
DEFAULT_THUMBS = 3  # the case's first, middle and last timestamps
NAME_ROUNDING_S = 5e-4  # a timestamp's name rounds its time to the millisecond


def _times(text: str | None, facts, models) -> list[float]:
    """``--times``: case seconds (``2.5``) or times of day (``10:15:07``), comma-separated;
    default the first, middle and last done timestamp."""
    from reconstructor.report.facts import ReportInputError

    entries = models.entries
    if text is None:
        picks = {0, len(entries) // 2, len(entries) - 1}
        return [entries[k].t_s for k in sorted(picks)][:DEFAULT_THUMBS]
    out = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        out.append(_one_time(part, facts))
    # a timestamp's name is its time to the millisecond: "2.133" means t00002.133 (2.1333 s)
    stored = [e.t_s for e in entries]
    out = [next((s for s in stored if abs(s - t) <= NAME_ROUNDING_S), t) for t in out]
    lo, hi = facts.span_s
    for t in out:
        if not lo - 1e-6 <= t <= hi + 1e-6:
            raise ReportInputError(
                f"--times: {t:.3f} s ({facts.clock.time_of_day(t)}) is outside the case, "
                f"{lo:.3f}-{hi:.3f} s ({facts.clock.time_of_day(lo)} to "
                f"{facts.clock.time_of_day(hi)})"
            )
    if not out:
        raise ReportInputError("--times is empty: give case seconds or times of day, a,b,c")
    return sorted(set(out))


def _one_time(part: str, facts) -> float:
    from reconstructor.report.facts import ReportInputError

    try:
        if ":" not in part:
            return float(part)
        clock = dt.time.fromisoformat(part)
    except ValueError:
        raise ReportInputError(
            f"--times: {part!r} is neither case seconds (2.5) nor a time of day (10:15:07)"
        ) from None
    start = facts.clock.at(0.0)
    when = dt.datetime.combine(start.date(), clock, tzinfo=start.tzinfo)
    return (when - start).total_seconds()


def main(argv: list[str]) -> int:
    p = command_parser("egosurg report", __doc__)
    p.add_argument("case", help="a case folder (egosurg reconstruct --every ... --out CASE/)")
    p.add_argument("--roles", help="a roles TOML: each role's view and its observed share")
    p.add_argument("--sterile", help="the folder 'egosurg sterile ... --out' wrote")
    p.add_argument("--sightline", action="append", default=[],
                   help="a folder 'egosurg sightline ... --out' wrote (repeatable)")  # fmt: skip
    p.add_argument("--times", help="when to show the role views: case seconds or HH:MM:SS, a,b")
    p.add_argument("--timezone", help="IANA zone of the times of day (default: this machine's)")
    add_identity_argument(p)
    p.add_argument("--out", required=True, help="the HTML file to write")
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.suffix.lower() not in (".html", ".htm"):
        raise CommandArgumentError(f"--out {out}: give an .html path")
    if out.is_dir():
        raise CommandArgumentError(f"--out {out} is a folder: give an .html file path")
    from reconstructor.replay.clock import pick_zone
    from reconstructor.report.build import build_report

    zone = pick_zone(args.timezone)
    identity = identity_from_args(args)
    command = "egosurg report " + shlex.join(argv)
    html, sealed = build_report(
        Path(args.case), roles=args.roles, sterile=args.sterile, sightlines=args.sightline,
        times=lambda facts, models: _times(args.times, facts, models), zone=zone,
        identity=identity, command=command,
    )  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(html, encoding="utf-8")
    make_owner_only(out)  # a report from an earlier run kept its mode when rewritten
    if sealed:
        print("warning: the session is sealed and no --identity was given: the report has no "
              "real camera frames and no case metadata (it says so at its top)",
              file=sys.stderr)  # fmt: skip
    print(f"wrote {out} (contains patient imagery)")
    return 0
