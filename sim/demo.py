"""``egosurg demo``: the whole chain on the simulated rig, stage by stage.

Example::

    egosurg demo --out out/demo

Stages so far:
1. build the simulated OR and write the rig's eight views, a top-down map and a ground-truth video;
2. run the capture chain as deployed: two simulated Jetson agents (two ZED X each) and the
   recorder as separate processes over loopback TCP; record about 10 s of the OR, stop, and print
   the session summary (``egosurg session info``).

Later capabilities (calibration, reconstruction, evaluation) add their stages here, each run
through the ``egosurg`` command as a user would run it.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from sim import pictures
from sim.cli import write_pictures
from sim.deploy import SimRig, SimRigSpec, write_sim_rig
from sim.world import World

STAGES = 2


def _stage(k: int, text: str) -> None:
    print(f"[{k}/{STAGES}] {text}", flush=True)


def stage_sim(out: Path, seed: int) -> None:
    _stage(1, "simulated OR: building the room, the rig and the people")
    world = World.from_seed(seed, phase="intraoperative")
    for u in world.rig:
        print(f"      camera SN{u.serial} on {u.node_id}")
    print(f"      people: {', '.join(s.name for s in world.people(0.0))}")
    paths = write_pictures(world, out / "sim", t_s=4.0, video_s=3.0, pictures=pictures)
    print("      wrote:")
    for p in paths:
        print(f"        {p}")


def stage_capture(out: Path, seed: int, record_s: float) -> Path:
    _stage(2, "capture: 2 agents + recorder as processes on loopback, recording the OR")
    files = write_sim_rig(
        out / "capture",
        SimRigSpec(seed=seed, fps=15.0, content_fps=1.0, prerender_s=record_s + 2.0),
    )
    for node, path in files.node_configs.items():
        print(f"      egosurg agent --config {path}        ({node})")
    print(f"      egosurg recorder --config {files.rig_config}")
    with SimRig(files) as rig:
        t0 = time.monotonic()
        rig.wait_streaming(timeout_s=600)
        print(f"      all 4 cameras streaming after {time.monotonic() - t0:.0f} s")
        started = rig.control("start", case="demo-case", meta={"procedure": "simulated"})
        print(f"      egosurg record start --case demo-case   -> {started['file']}")
        for k in range(int(record_s)):
            time.sleep(1.0)
            st = rig.control("status")
            print(
                f"\r      recording: {k + 1:>2}/{int(record_s)} s, {st['sets']} sets, "
                f"{st['bytes'] / 1e6:.0f} MB",
                end="",
                flush=True,
            )
        print()
        summary = rig.control("stop")
        print("      egosurg record stop")
    session = Path(summary["file"])
    print(f"      egosurg session info {session}")
    info = subprocess.run(
        [sys.executable, "-m", "protocol.cli", "session", "info", str(session)],
        capture_output=True,
        text=True,
        check=False,
    )
    print("\n".join("        " + line for line in info.stdout.splitlines()))
    if info.returncode != 0:
        print(info.stderr, file=sys.stderr)
    print(f"      logs: {files.directory / 'logs'}")
    return session


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="egosurg demo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument("--record-s", type=float, default=10.0, help="length of the recording")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    stage_sim(out, args.seed)
    stage_capture(out, args.seed, args.record_s)
    print(f"demo finished in {time.perf_counter() - t0:.0f} s; everything is under {out}/")
    return 0
