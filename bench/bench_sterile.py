"""Score ``egosurg sterile`` against the sim's truth: recall, false events (and per 10 minutes)
and start errors, the numbers of docs/replay.md's sterile-field tables.

An event is matched as in ``tests/reconstructor/test_sterile.py``: a true interval of the
scripted person (``--scripted``, the sim's radiographer) at least ``--min-touch`` long inside
the span is found when a contact event of the same person overlaps it (ending no more than
0.5 s before it starts); a contact event is false when no true interval of its role (anyone
non-sterile: a passer-by whose hip brushes the drape is in the field too) lies within 0.5 s
of it. ``--scripted ''`` counts every non-sterile person's time in the field as a touch.
Each found touch's start error is the
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
    scripted: str = "",
) -> SterileScore:
    """Recall over the true intervals of ``scripted`` (every non-sterile person's if ""); an
    event is false when it matches no true interval of anyone non-sterile."""
    contacts = [e for e in events if e["kind"] == "contact"]
    wanted = [(n, a, b) for n, a, b in truth if n not in sterile and b >= t0 and a <= t1]
    judged = [w for w in wanted if min(w[2], t1) - max(w[1], t0) >= min_touch_s]
    judged = [w for w in judged if not scripted or w[0] == scripted]
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


def plot(
    path: Path, rows: list[tuple[str, list[dict], list[tuple[str, float, float]], SterileScore]],
    sterile: set[str],
) -> None:  # fmt: skip
    """One panel per case: each non-sterile person's true intervals in the field (grey) above
    the contact events the tool reported for them (green when they match a true interval, red
    when false), on the case's time axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 1, figsize=(9, 1.0 + 1.1 * len(rows)), dpi=110,
                             squeeze=False)  # fmt: skip
    for ax, (label, events, truth, sc) in zip(axes[:, 0], rows, strict=True):
        people = sorted({n for n, _, _ in truth if n not in sterile}
                        | {e["role"] for e in events if e["kind"] == "contact"})  # fmt: skip
        false = {(n, a) for n, a, _ in sc.false}
        for y, person in enumerate(people):
            for n, a, b in truth:
                if n == person:
                    ax.broken_barh([(a, b - a)], (y + 0.05, 0.4), color="0.45")
            for e in events:
                if e["kind"] == "contact" and e["role"] == person:
                    a, b = float(e["start_s"]), float(e["end_s"])
                    colour = "tab:red" if (person, a) in false else "tab:green"
                    ax.broken_barh([(a - 0.1, b - a + 0.2)], (y - 0.45, 0.4), color=colour)
        ax.set_yticks(range(len(people)), people, fontsize=8)
        ax.set_ylim(-0.6, len(people) - 0.4)
        ax.set_title(f"{label}: recall {sc.found}/{sc.touches}, {sc.false_events} false "
                     "(grey: truth; green: found; red: false)", fontsize=9)  # fmt: skip
    axes[-1, 0].set_xlabel("case time (s)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


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
    ap.add_argument("--scripted", default="radiographer",
                    help="recall over this person's touches (the sim's scripted contact); "
                    "'' for every non-sterile person's time in the field")  # fmt: skip
    ap.add_argument("--label", default="", help="the row's name")
    ap.add_argument("--also", nargs=4, action="append", default=[],
                    metavar=("EVENTS", "TRUTH", "INSTANTS", "LABEL"),
                    help="another case in the same table (and plot)")  # fmt: skip
    ap.add_argument("--plot", type=Path, help="write the truth and the events as a PNG")
    args = ap.parse_args()
    sterile = set(args.sterile_roles.split(","))
    cases = [(args.events, args.truth, args.instants, args.label or str(args.events.parent))]
    cases += [(Path(e), Path(t), Path(i), lab) for e, t, i, lab in args.also]
    print("| case | recall | false events | per 10 min | start error (s) |")
    print("|---|---|---|---|---|")
    drawn, notes = [], []
    for events_csv, truth_csv, instants_csv, label in cases:
        events = _read_csv(events_csv)
        truth = [(r["person"], float(r["start_s"]), float(r["end_s"]))
                 for r in _read_csv(truth_csv)]  # fmt: skip
        if instants_csv:
            times = [float(r["t_s"]) for r in _read_csv(instants_csv)]
            t0, t1 = min(times), max(times)
        else:
            t0 = min(a for _, a, _ in truth)
            t1 = max(b for _, _, b in truth)
        sc = score(events, truth, sterile, t0, t1, args.min_touch, args.scripted)
        errors = ", ".join(f"{e:.2f}" for e in sc.start_errors_s) or "-"
        print(f"| {label} | {sc.found}/{sc.touches} | {sc.false_events} "
              f"| {sc.false_per_10_min:.0f} | {errors} |")  # fmt: skip
        notes += [f"{label}: missed {n} {a:.3f}-{b:.3f} s" for n, a, b in sc.missed]
        notes += [f"{label}: false {n} {a:.3f}-{b:.3f} s" for n, a, b in sc.false]
        drawn.append((label, events, truth, sc))
    print("\n".join(notes))
    if args.plot:
        plot(args.plot, drawn, sterile)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
