"""One change at a time: an evaluation's variant against its base, view by view.

Reads the job records (``OUT/jobs/*.json``, or any folders of them: a run spread over parts
leaves one per part) of a base run and of one or more variant runs made with one setting
changed, pairs the image scores by (view, method) on the views every run scored, and prints
EVALUATION.md's table: each row's mean ± SD over those views, the paired difference (variant -
base, mean ± SD) and how many views the variant scored higher, then the refinement stage's
worth (EgoSurg - "w/o refinement") in each run. Scores not in every run are left out, and
counted.

    python bench/compare_runs.py bench/results/eval_paper/egocentric \\
        --variant "fusion cap 100k=bench/results/eval_paper/fusion_cap/cap_100k" \\
        --variant "no cap (965k)=bench/results/eval_paper/fusion_cap/no_cap"
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reconstructor.evaluation.methods import METHODS
from reconstructor.evaluation.tables import stat

PSNR = "psnr_db"


def view_key(score: dict) -> str:
    """One view's name across runs: its scene, and its view where a scene has several (the
    near-field protocol scores each held-out camera of a timestamp under one scene)."""
    scene, view = score["scene"], score.get("view", score["scene"])
    return scene if view == scene else f"{scene}/{view}"


def read_scores(folders: list[Path], protocol: str) -> dict[tuple[str, str], dict]:
    """(view, method) -> image score, from every ``*.json`` job record under ``folders``."""
    scores: dict[tuple[str, str], dict] = {}
    for folder in folders:
        paths = sorted(folder.rglob("*.json"))
        records = [p for p in paths if p.parent.name == "jobs" or p.parent == folder]
        if not records:
            raise SystemExit(f"{folder}: no job records (*.json) found")
        for path in records:
            data = json.loads(path.read_text())
            for s in data.get("image_scores", []):
                if s["protocol"] == protocol:
                    scores[(view_key(s), s["method"])] = s
    return scores


def common_keys(runs: list[dict], methods: list[str]) -> tuple[list[tuple[str, str]], int]:
    """The (view, method) scores every run has, for ``methods``; and how many are left out."""
    wanted = [{k for k in run if k[1] in methods} for run in runs]
    common = set.intersection(*wanted)
    return sorted(common), len(set.union(*wanted) - common)


def values(run: dict, keys: list[tuple[str, str]], method: str, metric: str) -> list[float]:
    """``metric`` of ``method`` on each view of ``keys``, in their order."""
    return [run[k][metric] for k in keys if k[1] == method]


def refinement_worth(scores: dict, keys: list[tuple[str, str]]) -> list[float] | None:
    """EgoSurg - w/o refinement per view of one run (None unless it has both rows)."""
    scenes = [k[0] for k in keys if k[1] == "egosurg"]
    if not scenes or not any(k[1] == "no-refinement" for k in keys):
        return None
    return [scores[(s, "egosurg")][PSNR] - scores[(s, "no-refinement")][PSNR] for s in scenes]


def _ms(values: list[float], digits: int = 2) -> str:
    st = stat(values)
    return f"{st.mean:.{digits}f} ± {0.0 if st.n < 2 else st.sd:.{digits}f}"


def table(runs: list[tuple[str, dict]], keys: list[tuple[str, str]], methods: list[str]) -> str:
    """Markdown: per method, the base run's row then each variant's with its paired
    difference; then each run's refinement worth. ``runs[0]`` is the base."""
    lines = [
        "| row | PSNR (dB) | SSIM | paired difference (dB) | views better |",
        "|---|---|---|---|---|",
    ]
    base = runs[0][1]
    for m in methods:
        if not any(k[1] == m for k in keys):
            continue
        label = METHODS[m].label if m in METHODS else m
        base_db = values(base, keys, m, PSNR)
        for i, (name, run) in enumerate(runs):
            db, ssim = values(run, keys, m, PSNR), values(run, keys, m, "ssim")
            row = f"| {label}, {name} | {_ms(db)} | {_ms(ssim, 3)} |"
            if i == 0:
                lines.append(row + " | |")
                continue
            diff = [v - b for b, v in zip(base_db, db, strict=True)]
            better = sum(d > 0 for d in diff)
            lines.append(f"{row} {_ms(diff)} | {better} / {len(diff)} |")
    for name, run in runs:
        worth = refinement_worth(run, keys)
        if worth is not None:
            better = sum(w > 0 for w in worth)
            lines.append(
                f"| refinement's worth, {name} | | | {_ms(worth)} | {better} / {len(worth)} |"
            )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base", type=Path, nargs="+", help="the base run's job record folder(s)")
    ap.add_argument(
        "--variant",
        action="append",
        required=True,
        metavar="NAME=FOLDER[,FOLDER]",
        help="a variant run: its name in the table and its job record folder(s)",
    )
    ap.add_argument("--base-name", default="base", help="the base run's name in the table")
    ap.add_argument("--protocol", default="egocentric")
    ap.add_argument("--methods", nargs="+", default=["no-refinement", "egosurg"])
    args = ap.parse_args()
    runs = [(args.base_name, read_scores(args.base, args.protocol))]
    for spec in args.variant:
        name, sep, folders = spec.partition("=")
        if not sep or not folders:
            ap.error(f"--variant {spec!r}: write NAME=FOLDER, e.g. 'no cap=out/nocap/jobs'")
        runs.append((name, read_scores([Path(f) for f in folders.split(",")], args.protocol)))
    keys, left_out = common_keys([scores for _, scores in runs], args.methods)
    if not keys:
        ap.error(f"no view was scored by every run ({', '.join(args.methods)})")
    views = len({k[0] for k in keys})
    print(f"{views} views scored by every run; {left_out} scores left out (not in every run)")
    print(table(runs, keys, args.methods))
    return 0


if __name__ == "__main__":
    sys.exit(main())
