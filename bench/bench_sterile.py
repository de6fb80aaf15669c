"""Score ``egosurg sterile`` against the sim's truth: recall, false events (and per 10 minutes)
and start errors, the numbers of docs/replay.md's sterile-field tables.

An event is matched as in ``tests/reconstructor/test_sterile.py``: a true non-sterile interval
at least ``--min-touch`` long inside the span is found when a contact event of the same person
overlaps it (ending no more than 0.5 s before it starts); a contact event is false when no
true interval of its role lies within 0.5 s of it. Each found touch's start error is the
event's start minus the interval's.

Example (the commands that make the inputs are in docs/replay.md, "Sterile field")::

    .venv/bin/python bench/bench_sterile.py out7/events.csv truth.csv \\
        --sterile-roles surgeon,assistant,nurse_scrub --label "seed 7, 4 Hz"
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass
from pathlib import Path

MATCH_S = 0.5


@dataclass(frozen=True)
class SterileScore:
    touches: int  # true non-sterile intervals long enough to be judged
    found: int
    false_events: int
    span_s: float
    start_errors_s: tuple[float, ...]
    missed: tuple[tuple[str, float, float], ...]
    false: tuple[tuple[str, float, float], ...]

    @property
    def false_per_10_min(self) -> float:
        return self.false_events * 600.0 / self.span_s if self.span_s > 0 else float("nan")


def score(
    events: list[dict],
    truth: list[tuple[str, float, float]],
    sterile: set[str],
    t0: float,
    t1: float,
    min_touch_s: float,
) -> SterileScore:
    contacts = [e for e in events if e["kind"] == "contact"]
    wanted = [(n, a, b) for n, a, b in truth if n not in sterile and b >= t0 and a <= t1]
    judged = [w for w in wanted if min(w[2], t1) - max(w[1], t0) >= min_touch_s]
    errors, missed = [], []
    for name, a, b in judged:
        hits = [
            e
            for e in contacts
            if e["role"] == name
            and float(e["start_s"]) <= b + 1e-6
            and float(e["end_s"]) >= a - MATCH_S
        ]
        if hits:
            errors.append(float(hits[0]["start_s"]) - max(a, t0))
        else:
            missed.append((name, a, b))
    false = []
    for e in contacts:
        s, f = float(e["start_s"]), float(e["end_s"])
        if not any(n == e["role"] and s <= b + MATCH_S and f >= a - MATCH_S for n, a, b in wanted):
            false.append((e["role"], s, f))
    return SterileScore(
        touches=len(judged),
        found=len(judged) - len(missed),
        false_events=len(false),
        span_s=t1 - t0,
        start_errors_s=tuple(errors),
        missed=tuple(missed),
        false=tuple(false),
    )


def _read_csv(path: Path) -> list[dict]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("events", type=Path, help="egosurg sterile's events.csv")
    ap.add_argument("truth", type=Path, help="egosurg sim contact's truth.csv")
    ap.add_argument("--sterile-roles", default="surgeon,assistant,nurse_scrub")
    ap.add_argument("--instants", type=Path, help="instants.csv (the span; default: the truth's)")
    ap.add_argument("--min-touch", type=float, default=0.5, help="shortest touch judged, s")
    ap.add_argument("--label", default="", help="the row's name")
    args = ap.parse_args()
    events = _read_csv(args.events)
    truth = [(r["person"], float(r["start_s"]), float(r["end_s"])) for r in _read_csv(args.truth)]
    if args.instants:
        times = [float(r["t_s"]) for r in _read_csv(args.instants)]
        t0, t1 = min(times), max(times)
    else:
        t0 = min(a for _, a, _ in truth)
        t1 = max(b for _, _, b in truth)
    sc = score(events, truth, set(args.sterile_roles.split(",")), t0, t1, args.min_touch)
    errors = ", ".join(f"{e:.2f}" for e in sc.start_errors_s) or "-"
    print("| case | recall | false events | per 10 min | start error (s) |")
    print("|---|---|---|---|---|")
    print(
        f"| {args.label or args.events.parent} | {sc.found}/{sc.touches} | {sc.false_events} "
        f"| {sc.false_per_10_min:.0f} | {errors} |"
    )
    for name, a, b in sc.missed:
        print(f"missed: {name} {a:.3f}-{b:.3f} s")
    for name, a, b in sc.false:
        print(f"false: {name} {a:.3f}-{b:.3f} s")


if __name__ == "__main__":
    main()
