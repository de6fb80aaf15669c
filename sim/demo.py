"""``egosurg demo``: the whole chain on the simulated rig, stage by stage.

Example::

    egosurg demo --out out/demo

Stages so far:
1. build the simulated OR and write the rig's eight views, a top-down map and a ground-truth video.

Later capabilities (recording, calibration, reconstruction, evaluation) add their stages here,
each run through the ``egosurg`` command as a user would run it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from sim import pictures
from sim.cli import write_pictures
from sim.world import World


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="egosurg demo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    print("[1/1] simulated OR: building the room, the rig and the people")
    world = World.from_seed(args.seed, phase="intraoperative")
    for u in world.rig:
        print(f"      camera SN{u.serial} on {u.node_id}")
    print(f"      people: {', '.join(s.name for s in world.people(0.0))}")
    paths = write_pictures(world, out / "sim", t_s=4.0, video_s=3.0, pictures=pictures)
    print("      wrote:")
    for p in paths:
        print(f"        {p}")
    print(f"demo finished in {time.perf_counter() - t0:.0f} s; everything is under {out}/")
    return 0
