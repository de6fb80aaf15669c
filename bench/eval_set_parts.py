"""Split an evaluation set's timestamps into part manifests, to spread one evaluation over
processes or machines.

Each part is one scene's timestamps (its ``eval_sets`` and the sets its reference views are
at) in chunks of at most ``--per-part``, with the views at those sets and no temporal sets,
written beside the set's own manifest as ``eval_set.part-<scene>-<k>.toml``, so that it names
the same session files. Run
``egosurg evaluate <manifest> --out PART_OUT ...`` for each part (anywhere, with the same
options), copy every ``PART_OUT/jobs/*`` into one folder, and ``egosurg evaluate <the whole
set> --out THAT_FOLDER ... --resume`` writes the tables of the whole set, running only what no
part did (docs/evaluation.md, "Spreading a run"). A job's record is named by its scene and set,
so the parts' records are the whole set's.

    python bench/eval_set_parts.py out/evalset_ego --per-part 2 [--scenes setup setup-later]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.formats.eval_set import EvalSet


def parts(eval_set: EvalSet, per_part: int, scenes: list[str]) -> list[tuple[str, EvalSet]]:
    """(file name, part) for every chunk of every chosen scene's eval_sets."""
    out = []
    for scene in eval_set.scenes:
        if scenes and scene.name not in scenes:
            continue
        sets = sorted(set(scene.eval_sets) | {v.set_index for v in scene.views})
        for k in range(0, len(sets), per_part):
            chunk = tuple(sets[k : k + per_part])
            part = dataclasses.replace(
                scene,
                eval_sets=tuple(i for i in scene.eval_sets if i in chunk),
                temporal_sets=(),
                views=tuple(v for v in scene.views if v.set_index in chunk),
            )
            name = f"eval_set.part-{scene.name}-{k // per_part}.toml"
            out.append((name, dataclasses.replace(eval_set, scenes=(part,))))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("eval_set", help="the evaluation set's folder")
    ap.add_argument("--per-part", type=int, default=2, help="timestamps per part (2)")
    ap.add_argument("--scenes", nargs="+", default=[], help="only these scenes (all)")
    args = ap.parse_args()
    if args.per_part < 1:
        ap.error("--per-part must be at least 1")
    eval_set = EvalSet.read(args.eval_set)
    names = {s.name for s in eval_set.scenes}
    for s in args.scenes:
        if s not in names:
            ap.error(f"--scenes {s}: the set has no such scene; it has {', '.join(sorted(names))}")
    for name, part in parts(eval_set, args.per_part, args.scenes):
        path = eval_set.root / name
        path.write_text(part.to_toml())
        (scene,) = part.scenes
        sets = sorted(set(scene.eval_sets) | {v.set_index for v in scene.views})
        print(f"{path}: {scene.name} sets {sets}, {len(scene.views)} views")
    return 0


if __name__ == "__main__":
    sys.exit(main())
