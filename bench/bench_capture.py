"""Capture and recording throughput: the simulated rig as real processes, against the raw limits
of the same JPEG bytes through ZeroMQ, HDF5 and imagezmq, measured in the same run.

    .venv/bin/python bench/bench_capture.py [--duration-s 60] [--step-s 20] [--profile]
    .venv/bin/python bench/bench_capture.py --quick      # a smoke run of about two minutes

What it runs, in order, on loopback only:

1. The full rig: 4 stereo cameras, HD1200, 30 fps, JPEG pre-encoded by the sim source, from two
   ``egosurg agent`` processes into one ``egosurg recorder`` (``sim.deploy.SimRig``), recording
   for ``--duration-s``. Loss, latency and rates come from the recorder's stop summary; CPU from
   ``/proc/<pid>/stat`` (utime + stime) over the recording, in % of one core.
2. Raw limits on real HD1200 JPEG pairs read back from the session that run wrote: ZeroMQ
   PUSH/PULL and PUB/SUB (``copy=False``, one sender process, one receiver process),
   ``SessionWriter`` appending the frames with a flush every 0.5 s (with direct I/O, its
   default, and through the page cache), a plain file written in the same 1 MiB blocks
   (buffered, and with ``O_DIRECT``: what the disk takes), and imagezmq's REQ/REP
   sender-to-hub rate (one and two sender processes; the hub only receives and replies b"OK").
3. Load steps: the same rig with more offered load (fps up to the ZED X's 60 at HD1200, then more
   cameras per agent (``SimRigSpec.cameras``: extra cameras are the 4 cameras of the sim worlds
   of further seeds, so every camera has its own serial and clock). A step is sustained when no
   frame is lost (camera or agent drops + transport losses + frames of the take not written at
   the stop = 0) and the recorder stored at least 99% of the frames offered over the recording.
   Steps stop at the first one not sustained. A step at imagezmq's measured hub rate is added,
   so the goal is tested directly.
1b. CURVE's cost: the full rig again with plaintext links (``insecure = true``), in the same run:
   the stored-rate ratio (CURVE / plaintext) and both p99 capture-to-durable latencies; and the
   agents' load steps once more in plaintext (``--no-plaintext-steps`` skips them), so the
   highest sustained step with CURVE can be set against the plaintext one (target: >= 0.8x).
   Every other run uses CURVE, the default: agents, replay feeders and recorder are CURVE
   servers and clients with the keys ``sim.deploy.write_keys`` makes.
4. ``--profile``: the first step not sustained (else the highest step) again, with py-spy
   sampling the recorder; prints where its I/O thread spends its time.

The parts live in ``bench/capture/`` (measure, rigs, runs, limits, report); this script is the
command line and the order of the sections.

Everything runs on the same 2-core machine: the agents, the recorder and the kernel's page-cache
writeback share the cores, so absolute rates drift; read the ratios. Session files are deleted
after their numbers are read (``--keep`` keeps them); logs stay under ``--workdir``.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import math
import os
import platform
import sys
import time
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
if str(_ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(_ROOT))

from bench.capture import measure, rigs  # noqa: E402  (after the path, as a script)
from bench.capture.limits import (  # noqa: E402
    file_limit,
    hdf5_limit,
    imagezmq_limit,
    median_run,
    zmq_limit,
)
from bench.capture.measure import (  # noqa: E402
    BUSY_OTHER_CPU,
    MAX_FPS,
    REPLAY_FPS,
    RESOLUTION,
    RIG_CAMERAS,
    RIG_FPS,
    SUSTAIN_RATE,
    RunResult,
    fmt,
    log,
    wait_quiet,
)
from bench.capture.report import (  # noqa: E402
    Limits,
    curve_steps_line,
    curve_table,
    raw_table,
    rig_table,
    steps_table,
    summary,
)
from bench.capture.runs import run_recording  # noqa: E402

Pairs = list[tuple[bytes, bytes]]


def parse_steps(text: str) -> list[tuple[int, float]]:
    steps = []
    for item in text.split(","):
        cams, _, fps = item.strip().partition("x")
        steps.append((int(cams), float(fps)))
    return steps


def run_steps(
    steps, args, feed: str, pairs, rig: RunResult | None, insecure: bool = False
) -> list[RunResult]:
    results: list[RunResult] = []
    links = "-plaintext" if insecure else ""
    for k, (cams, fps) in enumerate(steps):
        if rig is not None and (cams, fps) == (rig.cameras, rig.fps):
            results.append(rig)  # measured in part 1, over a longer run
        else:
            for attempt in range(2):
                r = run_recording(
                    args.workdir / f"{feed}{links}{k}",
                    f"{feed}{links}-{cams}x{fps:g}",
                    cams,
                    fps,
                    args.step_s,
                    feed=feed,
                    pairs=pairs,
                    keep=args.keep,
                    insecure=insecure,
                )
                if r.other_cpu <= BUSY_OTHER_CPU or attempt == 1:
                    break
                log(f"other processes used {r.other_cpu:.0f}% of a core: running the step again")
                time.sleep(30.0)
            results.append(r)
        if not results[-1].sustained:
            break
    return results


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--duration-s", type=float, default=60.0, help="full-rig recording")
    parser.add_argument("--step-s", type=float, default=20.0, help="each load step's recording")
    parser.add_argument("--raw-s", type=float, default=5.0, help="each raw-limit measurement")
    parser.add_argument(
        "--steps",
        default="4x30,4x60,8x60,12x60,16x60,20x60",
        help="load steps with real agents, CAMERASxFPS (HD1200 allows up to 60 fps)",
    )
    parser.add_argument(
        "--replay-steps",
        default="4x120,6x120,8x120,10x120,12x120,16x120,20x120",
        help="load steps with replay feeders (fps up to rig.toml's 120); a step at imagezmq's "
        "measured rate is added",
    )
    parser.add_argument("--raw-repeats", type=int, default=3, help="median of this many")
    parser.add_argument("--quick", action="store_true", help="a short smoke run")
    parser.add_argument("--profile", action="store_true", help="py-spy the recorder at its limit")
    parser.add_argument(
        "--quiet-wait-s",
        type=float,
        default=120.0,
        help="before each measurement, wait at most this long for other processes to go quiet",
    )
    parser.add_argument(
        "--no-plaintext-steps",
        action="store_true",
        help="skip the agents' load steps with plaintext links (CURVE's cost at the limit)",
    )
    parser.add_argument(
        "--plaintext-sessions",
        action="store_true",
        help="record plaintext sessions (the default seals them for a site key, as a rig does)",
    )
    parser.add_argument("--keep", action="store_true", help="keep the session files")
    parser.add_argument("--workdir", type=Path, default=_ROOT / "out" / "bench_capture")
    args = parser.parse_args()
    if args.quick:
        args.duration_s, args.step_s, args.raw_s, args.raw_repeats = 8.0, 6.0, 1.5, 1
        args.steps, args.replay_steps = "4x30,8x60", "8x120,20x120"
    return args


def check_steps(args: argparse.Namespace) -> tuple[list, list]:
    """(agent steps, replay steps), each within what the camera and rig.toml allow."""
    steps, replay_steps = parse_steps(args.steps), parse_steps(args.replay_steps)
    for cams, fps in steps:
        if not 0 < fps <= MAX_FPS:
            raise SystemExit(f"step {cams}x{fps:g}: {RESOLUTION} allows 0 < fps <= {MAX_FPS:g}")
    for cams, fps in replay_steps:
        if not 0 < fps <= REPLAY_FPS:
            raise SystemExit(f"replay step {cams}x{fps:g}: rig.toml allows fps <= {REPLAY_FPS:g}")
    return steps, replay_steps


def require_imagezmq() -> None:
    try:
        import imagezmq  # noqa: F401  (the reference; imported here only to fail early)
    except ImportError:
        raise SystemExit(
            "bench_capture.py compares against imagezmq, which is not installed: "
            "run `make test` (it installs the bench extra) or `pip install -e '.[bench]'`"
        ) from None


def part1_full_rig(args: argparse.Namespace) -> tuple[RunResult, Pairs]:
    """The full rig with CURVE; its session's JPEG pairs feed every later part."""
    pairs: Pairs = []
    rig = run_recording(
        args.workdir / "rig",
        "rig",
        RIG_CAMERAS,
        RIG_FPS,
        args.duration_s,
        keep=args.keep,
        payload_out=pairs,
    )
    print(rig_table(rig))
    print()
    return rig, pairs


def part1b_plaintext(args: argparse.Namespace, rig: RunResult) -> RunResult:
    """CURVE against plaintext: the same rig in the same run."""
    plain = run_recording(
        args.workdir / "rig-plaintext",
        "rig-plaintext",
        RIG_CAMERAS,
        RIG_FPS,
        args.duration_s,
        keep=args.keep,
        insecure=True,
    )
    print(curve_table(rig, plain))
    print()
    return plain


def part2_raw_limits(args: argparse.Namespace, pairs: Pairs) -> Limits:
    """Every raw path on the same JPEGs, interleaved so drift hits every path alike; medians."""
    sizes = [len(b) for p in pairs for b in p]
    log(f"raw limits on {len(pairs)} real JPEG pairs ({min(sizes)}-{max(sizes)} bytes per image)")
    jpgs = [b for p in pairs for b in p]
    raw: dict[str, list[dict[str, float]]] = collections.defaultdict(list)
    for k in range(args.raw_repeats):
        wait_quiet(f"raw round {k + 1}")
        raw["push"].append(zmq_limit("push", pairs, args.raw_s))
        raw["pub"].append(zmq_limit("pub", pairs, args.raw_s))
        raw["h5"].append(hdf5_limit(pairs, args.raw_s, args.workdir / "raw"))
        raw["h5c"].append(hdf5_limit(pairs, args.raw_s, args.workdir / "raw", direct_io=False))
        raw["file"].append(file_limit(pairs, args.raw_s, args.workdir / "raw"))
        raw["disk"].append(file_limit(pairs, args.raw_s, args.workdir / "raw", direct=True))
        raw["iz1"].append(imagezmq_limit(jpgs, args.raw_s, senders=1))
        raw["iz2"].append(imagezmq_limit(jpgs, args.raw_s, senders=2))
        log(
            f"raw round {k + 1}: PUSH/PULL {raw['push'][-1]['msgs_s']:.0f} stereo/s, PUB/SUB "
            f"{raw['pub'][-1]['msgs_s']:.0f}, HDF5 {raw['h5'][-1]['frames_s']:.0f} (through the "
            f"page cache {raw['h5c'][-1]['frames_s']:.0f}), plain file "
            f"{raw['file'][-1]['frames_s']:.0f} (direct {raw['disk'][-1]['frames_s']:.0f}), "
            "imagezmq "
            f"{raw['iz1'][-1]['images_s']:.0f} / {raw['iz2'][-1]['images_s']:.0f} images/s"
        )
    key = {"push": "msgs_s", "pub": "msgs_s", "iz1": "images_s", "iz2": "images_s"}
    limits = {path: median_run(runs, key.get(path, "frames_s")) for path, runs in raw.items()}
    image_kb = sum(sizes) / len(sizes) / 1e3
    print(raw_table(limits, len(pairs), image_kb, args.raw_s, args.raw_repeats))
    print()
    return limits


def part3a_agent_steps(
    args: argparse.Namespace, steps: list, pairs: Pairs, rig: RunResult, plain: RunResult
) -> list[RunResult]:
    """Load steps with the real agents, with CURVE and (unless skipped) in plaintext."""
    results = run_steps(steps, args, "agents", pairs, rig)
    print(
        f"### 3a. Load steps with the real agents ({args.step_s:g} s each; sustained = 0 lost "
        f"and a stored rate >= {100 * SUSTAIN_RATE:.0f}% of the offered rate between two "
        "status polls inside the recording; a step during which the rest of the machine used "
        f"more than {BUSY_OTHER_CPU:g}% of a core is run once more, and marked if it stays busy)\n"
    )
    print(steps_table(results, rig))
    print()
    if not args.no_plaintext_steps:
        plain_results = run_steps(steps, args, "agents", pairs, plain, insecure=True)
        print("### 3a'. The same load steps with plaintext links (insecure = true)\n")
        print(steps_table(plain_results, plain))
        print()
        print(curve_steps_line(results, plain_results))
        print()
    return results


def part3b_replay_steps(
    args: argparse.Namespace, replay_steps: list, pairs: Pairs, images_s: float
) -> list[RunResult]:
    """Load steps with replay feeders, one of them at imagezmq's measured ``images_s``."""
    # the fewest cameras (an even number: two feeders) that offer imagezmq's rate exactly
    goal_cams = 2 * math.ceil(images_s / 2 / REPLAY_FPS / 2)
    goal_fps = math.ceil(images_s / 2 / goal_cams * 10) / 10  # up: never below the reference
    if (goal_cams, goal_fps) not in replay_steps:
        replay_steps.append((goal_cams, goal_fps))
    replay_steps.sort(key=lambda s: (s[0] * s[1], s[0]))
    replayed = run_steps(replay_steps, args, "replay", pairs, None)
    lags = ", ".join(f"{r.cameras}x{r.fps:g}: {fmt(r.feeder_lag_ms, '.0f')}" for r in replayed)
    print(
        "### 3b. Load steps with replay feeders (two processes that publish the same frame "
        "messages without rendering or per-frame validation, so the recorder gets more of the "
        f"2 cores; the worst feeder lag in ms was {lags})\n"
    )
    print(steps_table(replayed, None))
    print()
    return replayed


def part4_profile(
    args: argparse.Namespace, results: list[RunResult], replayed: list[RunResult], pairs: Pairs
) -> None:
    """py-spy of the recorder at the first step not sustained (else the highest step)."""
    failing = [r for r in replayed if not r.sustained] or [r for r in results if not r.sustained]
    target = failing[0] if failing else replayed[-1]
    profiled = run_recording(
        args.workdir / "profile",
        f"profile-{target.feed}-{target.cameras}x{target.fps:g}",
        target.cameras,
        target.fps,
        args.step_s,
        feed=target.feed,
        pairs=pairs,
        keep=args.keep,
        profile=True,
    )
    print(
        f"### 4. py-spy of the recorder at {target.cameras} x {target.fps:g} fps "
        f"({target.feed}; a rerun with py-spy attached: {profiled.steady_rate:.0f} of "
        f"{profiled.offered_rate:g} stereo/s stored, {profiled.lost} lost, recorder CPU "
        f"{profiled.recorder_cpu:.0f}%)\n"
    )
    print(profiled.profile)
    print()


def main() -> None:
    args = parse_args()
    measure.QUIET_WAIT_S[0] = args.quiet_wait_s
    rigs.PLAINTEXT_SESSIONS[0] = args.plaintext_sessions
    require_imagezmq()
    steps, replay_steps = check_steps(args)
    args.workdir.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    print(
        f"Run on {datetime.date.today().isoformat()}: {os.cpu_count()} cores, "
        f"{platform.python_implementation()} {platform.python_version()}; command: "
        f"`.venv/bin/python bench/bench_capture.py {' '.join(sys.argv[1:])}`.\n"
    )
    rig, pairs = part1_full_rig(args)
    plain = part1b_plaintext(args, rig)
    limits = part2_raw_limits(args, pairs)
    results = part3a_agent_steps(args, steps, pairs, rig, plain)
    replayed = part3b_replay_steps(args, replay_steps, pairs, limits["iz1"]["images_s"])
    if args.profile:
        part4_profile(args, results, replayed, pairs)
    print(summary(rig, results, replayed, limits))
    print(f"\nTotal time: {(time.monotonic() - t_start) / 60:.1f} min")


if __name__ == "__main__":
    main()
