"""A stereo setting's worth downstream: evaluation runs that differ only in their ``[stereo]``
table, compared view by view, and each setting's depth stage timed on the same timestamps.

Reads the job records (``OUT/jobs/*.json``, any number of folders per run: one per scene when
the runs were made scene by scene) of a base run and of runs made with another stereo config on
the same evaluation set, pairs every image score by (protocol, scene, view, method), and prints:

1. per protocol and method, each run's PSNR / SSIM (mean ± SD over the scenes as ``egosurg
   evaluate`` tables them: a near-field timestamp's four cameras, an egocentric view), the
   paired difference against the base over the views, and how many views got better; for
   depth reprojection also its holes and its PSNR over the pixels it drew;
2. per protocol, every view: the base's PSNR and each run's difference, for each method, and
   depth reprojection's holes and drawn PSNR, so a loss can be traced to a camera or a person;
3. with ``--time-depth EVALSET``, each run's depth stage (stereo on every pair, the fill and
   the fusion, as ``egosurg evaluate`` makes it) timed on every timestamp the records scored,
   the configs alternating, ``--repeat`` times, with each camera's share of valid pixels and the
   ratio of each run's seconds to the base's.

    python bench/bench_stereo_downstream.py \\
        --run "default=out/sd/default/intraoperative,out/sd/default/setup" \\
        --run "densest=out/sd/densest/intraoperative,out/sd/densest/setup" \\
        --time-depth out/evalset_sd --repeat 2

The runs' configs are read from their records (``settings.config``, relative to where the
evaluation ran: run this from the same folder).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reconstructor.evaluation.methods import METHODS

Key = tuple[str, str, str, str]  # protocol, scene, view, method


def read_run(folders: list[Path]) -> tuple[dict[Key, dict], set[str], dict]:
    """(protocol, scene, view, method) -> image score; the configs named; one record's settings."""
    scores: dict[Key, dict] = {}
    configs: set[str] = set()
    settings: dict = {}
    for folder in folders:
        paths = [p for p in sorted(folder.rglob("*.json")) if p.parent.name == "jobs"]
        if not paths:
            raise FileNotFoundError(f"{folder}: no job records (jobs/*.json); give an --out folder")
        for path in paths:
            data = json.loads(path.read_text())
            settings = data.get("settings", {})
            configs.add(settings.get("config", ""))
            for s in data.get("image_scores", []):
                scores[(s["protocol"], s["scene"], s["view"], s["method"])] = s
    return scores, configs, settings


def _label(method: str) -> str:
    return METHODS[method].label if method in METHODS else method


def _ms(values: list[float], digits: int = 2) -> str:
    v = np.asarray(values, np.float64)
    sd = float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
    return f"{v.mean():.{digits}f} ± {sd:.{digits}f}"


def _per_scene(run: dict[Key, dict], keys: list[Key], metric: str) -> list[float]:
    """The mean of each scene's views: a near-field scene is a timestamp (its four held-out
    cameras), an egocentric one a single person's view, as ``egosurg evaluate`` tables them."""
    by_scene: dict[str, list[float]] = defaultdict(list)
    for k in keys:
        by_scene[k[1]].append(run[k][metric])
    return [float(np.mean(v)) for v in by_scene.values()]


def summary(runs: list[tuple[str, dict[Key, dict]]], keys: list[Key]) -> str:
    """Table 1: per protocol and method, each run against the base."""
    lines = [
        "| protocol | row | run | PSNR (dB) | SSIM | paired difference (dB) | views better | "
        "holes % | drawn PSNR (dB) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    base = runs[0][1]
    for protocol in sorted({k[0] for k in keys}):
        for method in sorted({k[3] for k in keys if k[0] == protocol}):
            mk = [k for k in keys if k[0] == protocol and k[3] == method]
            n_scenes = len({k[1] for k in mk})
            for i, (name, run) in enumerate(runs):
                db = _per_scene(run, mk, "psnr_db")
                ssim = _per_scene(run, mk, "ssim")
                diff = [run[k]["psnr_db"] - base[k]["psnr_db"] for k in mk]
                paired = "" if i == 0 else _ms(diff)
                better = "" if i == 0 else f"{sum(d > 0 for d in diff)} / {len(diff)}"
                holes = drawn = ""
                if run[mk[0]].get("holes") is not None:
                    holes = f"{100 * np.mean([run[k]['holes'] for k in mk]):.1f}"
                    drawn = f"{np.mean([run[k]['drawn_psnr_db'] for k in mk]):.2f}"
                lines.append(
                    f"| {protocol} ({n_scenes} scenes, {len(mk)} views) | {_label(method)} | "
                    f"{name} | {_ms(db)} | {_ms(ssim, 3)} | {paired} | {better} | "
                    f"{holes} | {drawn} |"
                )
    return "\n".join(lines)


def per_view(runs: list[tuple[str, dict[Key, dict]]], keys: list[Key], protocol: str) -> str:
    """Table 2: every view of one protocol, the base's PSNR and each run's difference."""
    methods = sorted({k[3] for k in keys if k[0] == protocol})
    names = [name for name, _ in runs[1:]]
    head = ["timestamp", "view"]
    for m in methods:
        head += [f"{_label(m)} {runs[0][0]} dB"] + [f"{n} - {runs[0][0]}" for n in names]
        if m == "depth-reprojection":
            head += [f"holes % {runs[0][0]}"] + [f"holes {n}" for n in names]
            head += [f"drawn dB {runs[0][0]}"] + [f"drawn {n} - {runs[0][0]}" for n in names]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    base = runs[0][1]
    views = sorted({(k[1], k[2]) for k in keys if k[0] == protocol})
    for scene, view in views:
        row = [scene, view]
        for m in methods:
            k = (protocol, scene, view, m)
            row.append(f"{base[k]['psnr_db']:.2f}")
            row += [f"{run[k]['psnr_db'] - base[k]['psnr_db']:+.2f}" for _, run in runs[1:]]
            if m == "depth-reprojection":
                row += [f"{100 * run[k]['holes']:.1f}" for _, run in runs]
                row.append(f"{base[k]['drawn_psnr_db']:.2f}")
                row += [
                    f"{run[k]['drawn_psnr_db'] - base[k]['drawn_psnr_db']:+.2f}"
                    for _, run in runs[1:]
                ]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def time_depth(
    evalset: Path, configs: list[tuple[str, str]], scenes: list[str], repeat: int
) -> str:
    """Table 3: each config's depth stage (stereo, fill, fusion) on each scored timestamp."""
    from protocol.formats.eval_set import EvalSet
    from reconstructor.config import ReconstructConfig
    from reconstructor.depth.fusion import fuse
    from reconstructor.evaluation.runner import EvalSource
    from reconstructor.pipeline import stereo_clouds

    source = EvalSource(EvalSet.read(evalset))
    seconds: dict[tuple[str, str], list[float]] = defaultdict(list)
    valid: dict[tuple[str, str], dict[str, float]] = {}
    for scene_set in scenes:
        scene, _, set_index = scene_set.partition("@set")  # "intraoperative@set0"
        ts = source.timestamp(scene, int(set_index))
        bounds = list(source.scene(scene).room_bounds_m)
        for _ in range(repeat):
            for name, path in configs:
                start = ReconstructConfig.read(path) if path else ReconstructConfig()
                cfg = start.overridden({"room_bounds_m": bounds}, "the scene's room box")
                cfg = cfg.resolved(ts.resolution.width)
                t0 = time.perf_counter()
                clouds, depths = stereo_clouds(ts, cfg)
                fuse(clouds, cfg.fusion)
                seconds[(scene_set, name)].append(time.perf_counter() - t0)
                valid[(scene_set, name)] = {c: d.valid_fraction for c, d in depths.items()}
    base = configs[0][0]
    cams = sorted(next(iter(valid.values())))
    lines = [
        "| timestamp | run | depth stage s (min of "
        f"{repeat}) | x {base} | " + " | ".join(f"{c} valid %" for c in cams) + " |",
        "|---|---|---|---|" + "---|" * len(cams),
    ]
    for scene_set in scenes:
        for name, _ in configs:
            s = min(seconds[(scene_set, name)])
            ratio = s / min(seconds[(scene_set, base)])
            shares = " | ".join(f"{100 * valid[(scene_set, name)][c]:.1f}" for c in cams)
            lines.append(f"| {scene_set} | {name} | {s:.2f} | {ratio:.2f} | {shares} |")
    for name, _ in configs:
        s = [min(seconds[(t, name)]) for t in scenes]
        b = [min(seconds[(t, base)]) for t in scenes]
        lines.append(f"| mean | {name} | {np.mean(s):.2f} | {np.mean(s) / np.mean(b):.2f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--run",
        action="append",
        required=True,
        metavar="NAME=FOLDER[,FOLDER]",
        help="a run: its name and its evaluate --out folder(s); the first is the base",
    )
    ap.add_argument("--time-depth", type=Path, metavar="EVALSET", help="also time the depth stage")
    ap.add_argument("--repeat", type=int, default=1, help="depth stage timings per config")
    args = ap.parse_args()
    if len(args.run) < 2:
        ap.error("give at least two --run: the base and one other stereo setting")
    if args.repeat < 1:
        ap.error(f"--repeat {args.repeat}: give 1 or more")
    runs: list[tuple[str, dict[Key, dict]]] = []
    configs: list[tuple[str, str]] = []
    for spec in args.run:
        name, sep, folders = spec.partition("=")
        if not sep or not folders:
            ap.error(f"--run {spec!r}: write NAME=FOLDER[,FOLDER], e.g. 'default=out/sd/default'")
        missing = [f for f in folders.split(",") if not Path(f).is_dir()]
        if missing:
            ap.error(f"--run {name}: no folder {missing[0]}")
        try:
            scores, named, _ = read_run([Path(f) for f in folders.split(",")])
        except FileNotFoundError as exc:
            ap.error(f"--run {name}: {exc}")
        if len(named) != 1:
            ap.error(f"--run {name}: its records name {len(named)} configs ({sorted(named)})")
        runs.append((name, scores))
        configs.append((name, named.pop()))
    common = sorted(set.intersection(*(set(r) for _, r in runs)))
    left_out = len(set.union(*(set(r) for _, r in runs))) - len(common)
    if not common:
        ap.error("no view was scored by every run: were they made on the same evaluation set?")
    print(f"{len(common)} scores in every run, {left_out} left out (not in every run)")
    print("runs: " + ", ".join(f"{n} ({c or 'defaults'})" for n, c in configs) + "\n")
    print(summary(runs, common) + "\n")
    for protocol in sorted({k[0] for k in common}):
        print(f"{protocol}, per view:\n" + per_view(runs, common, protocol) + "\n")
    if args.time_depth is not None:
        if not (args.time_depth / "eval_set.toml").is_file():
            ap.error(f"--time-depth {args.time_depth}: no eval_set.toml there")
        # a timestamp: "<scene>@set<i>"; an egocentric view's scene adds "/<person>@<i>"
        scenes = sorted({k[1].split("/")[0] for k in common if "@set" in k[1]})
        print(time_depth(args.time_depth, configs, scenes, args.repeat))
    return 0


if __name__ == "__main__":
    sys.exit(main())
