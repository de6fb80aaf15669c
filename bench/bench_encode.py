"""JPEG encoding of HD1200 stereo pairs on the agent: the budget of 2 cameras x 30 fps.

    .venv/bin/python bench/bench_encode.py            # ~1 min (+ ~30 s to render the pair once)
    .venv/bin/python bench/bench_encode.py --quick    # ~10 s once the pair is cached

The pair: the sim's unit 0 at t = 1 s (``World.from_seed(11)``, HD1200, sensor noise on), in BGR
as the sim source gives it; rendering takes 15-30 s on 2 busy cores, so it is cached in
``--cache``. Each repeat measures, one after the other so their ratios share the machine's load:

- ``imencode``: ``cv2.imencode`` alone, the agent's parameters (quality 90, 4:4:4), left then
  right image, one thread; ``imencode 4:2:0``: the same at OpenCV's default chroma subsampling
  (what the 4:4:4 that wand detection needs costs);
- ``BGRA->BGR``: the ZED source's two ``cvtColor`` copies per pair (its grab thread's share);
- ``encode_pair``: ``protocol.images.encode_pair``, back to back in one thread (the reference);
- ``agent``: the real ``Agent`` (two camera worker threads encoding, one publisher, control,
  watchdog) with two cameras configured as a Jetson node's (``source = "zed"``, HD1200, 30 fps,
  ``buffer_frames = 2``). Only the SDK is replaced (``make_source``): each camera is a
  free-running 30 fps clock serving the cached pair, stamping frame i at its own time whoever
  reads it, and losing the oldest frame when the reader is ``buffer_frames`` behind, as the ZED
  source's grab thread does. Both cameras expose at the same instants (their encodes collide:
  the worst case). Nobody subscribes, so the publisher's sends are cheap.

CPU time (``time.thread_time`` around each encode) is the per-core measure: on a shared machine
wall time includes waiting for a core, CPU time hardly does. Wall ms per pair (p50, p99) say what
this machine's load did to the frames. Nothing here asserts a time; the Orin lines are
arithmetic on this run's per-core rate and the stated assumptions (``--per-clock``, ``--x86-ghz``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from capture_agent.agent import agent as agent_module
from capture_agent.sources.base import CameraSource, GrabbedFrame, require_timeout
from protocol.camera import Resolution
from protocol.formats.camera_config import CameraConfig
from protocol.formats.node_config import NodeConfig
from protocol.images import encode_pair

FPS = 30.0
CAMERAS = 2
QUALITY = 90
JPEG_444 = [
    int(cv2.IMWRITE_JPEG_QUALITY),
    QUALITY,
    int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR),
    int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
]
JPEG_420 = [int(cv2.IMWRITE_JPEG_QUALITY), QUALITY]
# (name, cores, GHz): Jetson Orin NX 16 GB and Orin Nano 8 GB, their CPUs' top clocks
DEVICES = (("Orin NX", 8, 2.0), ("Orin Nano", 6, 1.5))
Pair = tuple[np.ndarray, np.ndarray]
Sample = tuple[float, float]  # (wall ms, CPU ms) of one pair


def load_pair(cache: Path) -> Pair:
    """The sim's HD1200 pair in BGR (rendered once, then read from ``cache``)."""
    path = cache / "sim11_unit0_t1_hd1200.npz"
    if not path.exists():
        from sim import World

        print(f"rendering the HD1200 pair once into {path} (15-30 s) ...", file=sys.stderr)
        left, right = World.from_seed(11).render_stereo(0, 1.0, "HD1200")
        cache.mkdir(parents=True, exist_ok=True)
        np.savez(
            path,
            left=cv2.cvtColor(left.image_rgb, cv2.COLOR_RGB2BGR),
            right=cv2.cvtColor(right.image_rgb, cv2.COLOR_RGB2BGR),
        )
    with np.load(path) as data:
        return data["left"], data["right"]


def timed(fn: Callable[[], object], samples: list[Sample]) -> None:
    wall, cpu = time.perf_counter_ns(), time.thread_time_ns()
    fn()
    samples.append(((time.perf_counter_ns() - wall) / 1e6, (time.thread_time_ns() - cpu) / 1e6))


def loop_for(window_s: float, fn: Callable[[], object]) -> list[Sample]:
    """``fn`` (one pair's work) back to back in this thread for ``window_s`` (at least 3 times)."""
    samples: list[Sample] = []
    end = time.perf_counter() + window_s
    while time.perf_counter() < end or len(samples) < 3:
        timed(fn, samples)
    return samples


def references(pair: Pair, window_s: float) -> dict[str, list[Sample]]:
    left, right = pair
    bgra = [cv2.cvtColor(im, cv2.COLOR_BGR2BGRA) for im in pair]
    return {
        "imencode, 4:4:4": loop_for(
            window_s, lambda: [cv2.imencode(".jpg", im, JPEG_444) for im in pair]
        ),
        "imencode, 4:2:0": loop_for(
            window_s, lambda: [cv2.imencode(".jpg", im, JPEG_420) for im in pair]
        ),
        "BGRA->BGR (ZED source)": loop_for(
            window_s, lambda: [cv2.cvtColor(im, cv2.COLOR_BGRA2BGR) for im in bgra]
        ),
        "encode_pair, 1 thread": loop_for(
            window_s, lambda: encode_pair(left, right, "jpeg", QUALITY)
        ),
    }


class ClockedPairSource(CameraSource):
    """A free-running camera serving one pair: the bench's stand-in for the ZED SDK.

    Frame i is stamped ``t0 + i / fps`` (the camera's clock, before the agent encodes anything);
    a reader more than ``buffer_frames`` frames behind loses the oldest (``overrun_frames``) and
    the next frame's index jumps, as with the ZED source's grab thread and its small queue.
    """

    def __init__(self, entry: CameraConfig, pair: Pair, t0_unix_ns: int) -> None:
        self._serial = int(getattr(entry, "serial", None) or 1)
        self._fps = float(entry.fps or FPS)
        self._buffer = int(getattr(entry, "buffer_frames", 2))
        self._pair = pair
        self._t0 = t0_unix_ns
        self._open = False
        self.next_index = 0  # the next frame this reader gets, unless it is lost first
        self.overrun_frames = 0

    serial = property(lambda self: self._serial)
    resolution = property(lambda self: Resolution.HD1200)
    fps = property(lambda self: self._fps)
    is_open = property(lambda self: self._open)

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def factory_conf_text(self) -> str:
        return ""

    def grab(self, timeout_s: float) -> GrabbedFrame | None:
        period_ns = 1e9 / self._fps
        now = time.time_ns()
        newest = int((now - self._t0) // period_ns)  # the last frame already complete
        oldest_kept = newest - self._buffer + 1
        if self.next_index < oldest_kept:
            self.overrun_frames += oldest_kept - self.next_index
            self.next_index = oldest_kept
        stamp_ns = self._t0 + round(self.next_index * period_ns)
        wait_s = (stamp_ns - now) / 1e9
        if wait_s > require_timeout(timeout_s):
            time.sleep(timeout_s)
            return None
        if wait_s > 0:
            time.sleep(wait_s)
        self.next_index += 1
        return GrabbedFrame(
            frame_index=self.next_index - 1,
            capture_unix_ns=stamp_ns,
            host_receive_unix_ns=time.time_ns(),
            left_bgr=self._pair[0],
            right_bgr=self._pair[1],
        )


def node_config() -> NodeConfig:
    from sim.deploy import free_ports

    frames, control = free_ports(2)
    cameras = [
        {"source": "zed", "serial": 40_000_001 + i, "resolution": "HD1200", "fps": int(FPS)}
        for i in range(CAMERAS)
    ]
    table = {
        "node_id": "bench",
        "frames_bind": f"tcp://127.0.0.1:{frames}",
        "control_bind": f"tcp://127.0.0.1:{control}",
        "jpeg_quality": QUALITY,
        "ptp": {"source": "none", "require_lock": False},
        "cameras": cameras,
        "security": {"insecure": True},
    }
    return NodeConfig.from_table(table, "bench_encode node")


def run_agent(pair: Pair, warmup_s: float, window_s: float) -> dict:
    """The agent streaming for ``window_s`` after ``warmup_s``: its encodes, counters, CPU."""
    samples: list[Sample] = []
    recording = threading.Event()
    t0_unix_ns = time.time_ns()

    def timed_encode(*args: object, **kwargs: object):  # the agent's own call, timed
        wall, cpu = time.perf_counter_ns(), time.thread_time_ns()
        out = encode_pair(*args, **kwargs)  # type: ignore[arg-type]
        if recording.is_set():
            samples.append(
                ((time.perf_counter_ns() - wall) / 1e6, (time.thread_time_ns() - cpu) / 1e6)
            )
        return out

    sources: list[ClockedPairSource] = []  # every one made, a watchdog replacement included

    def make_source(config: CameraConfig) -> CameraSource:
        sources.append(ClockedPairSource(config, pair, t0_unix_ns))
        return sources[-1]

    saved = agent_module.make_source, agent_module.encode_pair
    agent_module.make_source = make_source
    agent_module.encode_pair = timed_encode
    agent = agent_module.Agent(node_config())
    try:
        agent.start()
        time.sleep(warmup_s)
        before = [w.status(0) for w in agent.workers]
        overrun0 = sum(s.overrun_frames for s in sources)
        cpu0, wall0 = time.process_time(), time.perf_counter()
        recording.set()
        time.sleep(window_s)
        recording.clear()
        cpu_s, wall_s = time.process_time() - cpu0, time.perf_counter() - wall0
        after = [w.status(0) for w in agent.workers]
        overrun = sum(s.overrun_frames for s in sources) - overrun0
        pairs = list(zip(after, before, strict=True))
    finally:
        agent.stop()
        agent_module.make_source, agent_module.encode_pair = saved
    return {
        "samples": samples,
        "cores_used": cpu_s / wall_s,
        "wall_s": wall_s,
        **{
            key: sum(getattr(a, f"frames_{key}") - getattr(b, f"frames_{key}") for a, b in pairs)
            for key in ("captured", "dropped", "published")
        },
        "overrun": overrun,
        "fps_measured": [a.fps_measured for a in after],
    }


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def row(name: str, samples: list[Sample], ref_cpu_ms: float) -> dict:
    wall, cpu = [s[0] for s in samples], [s[1] for s in samples]
    return {
        "name": name,
        "n": len(samples),
        "wall_p50": pct(wall, 50),
        "wall_p99": pct(wall, 99),
        "cpu_p50": pct(cpu, 50),
        "cpu_p99": pct(cpu, 99),
        "images_per_cpu_s": 2000.0 * len(cpu) / sum(cpu) if sum(cpu) > 0 else float("nan"),
        "cpu_ratio": pct(cpu, 50) / ref_cpu_ms,
    }


def one_repeat(pair: Pair, window_s: float) -> tuple[list[dict], dict]:
    refs = references(pair, window_s)
    ref_cpu = pct([s[1] for s in refs["encode_pair, 1 thread"]], 50)
    agent = run_agent(pair, warmup_s=1.0, window_s=2 * window_s)
    rows = [row(name, s, ref_cpu) for name, s in refs.items()]
    rows.append(row(f"agent, {CAMERAS} cameras x {FPS:g} fps", agent["samples"], ref_cpu))
    return rows, agent


def print_table(repeats: list[list[dict]]) -> None:
    """Medians over the repeats; the CPU ratio is to ``encode_pair, 1 thread`` of the same
    repeat (per pair; 'images' are the pair's two images)."""
    print(
        "| measure | ms per pair p50 / p99 (wall) | CPU ms per pair p50 / p99 "
        "| images per CPU-second | CPU ratio to encode_pair |"
    )
    print("|---|---:|---:|---:|---:|")
    for i, first in enumerate(repeats[0]):

        def med(key: str, i: int = i) -> float:
            return statistics.median(rep[i][key] for rep in repeats)

        print(
            f"| {first['name']} | {med('wall_p50'):.1f} / {med('wall_p99'):.1f} "
            f"| {med('cpu_p50'):.1f} / {med('cpu_p99'):.1f} | {med('images_per_cpu_s'):.0f} "
            f"| {med('cpu_ratio'):.2f} |"
        )


def print_agent(agents: list[dict]) -> None:
    for k, a in enumerate(agents, 1):
        expected = CAMERAS * FPS * a["wall_s"]
        print(
            f"- agent, repeat {k}: {a['wall_s']:.1f} s, camera clocks ~{expected:.0f} frames; "
            f"encoded {a['captured']}, agent frames_dropped {a['dropped']} (source overruns "
            f"{a['overrun']}), published {a['published']}; fps_measured "
            f"{', '.join(f'{f:g}' for f in a['fps_measured'])}; process CPU "
            f"{a['cores_used']:.2f} cores"
        )


def print_budget(cpu_ms: float, bgra_ms: float, x86_ghz: tuple, per_clock: tuple) -> None:
    """Each camera's pairs are encoded one after another in its worker thread, so a pair must
    fit one frame period on ONE core, however many cores the device has."""
    period_ms = 1000.0 / FPS
    print(
        f"\nBudget from this run: encode_pair {cpu_ms:.1f} CPU ms per pair here "
        f"({2000.0 / cpu_ms:.0f} images per CPU-second), + {bgra_ms:.1f} ms of BGRA->BGR; "
        f"assumed: this core at {x86_ghz[0]:g}-{x86_ghz[1]:g} GHz, an A78AE core "
        f"{per_clock[0]:g}-{per_clock[1]:g}x its work per clock."
    )
    need = CAMERAS * FPS * 2
    for name, cores, ghz in DEVICES:
        # best: fast A78AE per clock, this core at its lowest clock; worst: the opposite
        slow = [x86_ghz[0] / (ghz * per_clock[1]), x86_ghz[1] / (ghz * per_clock[0])]
        pair_ms = [cpu_ms * s for s in slow]
        used = [CAMERAS * FPS * (cpu_ms + bgra_ms) * s / 1000.0 for s in slow]
        kept = [min(FPS, 1000.0 / ms) for ms in pair_ms]
        print(
            f"- {name} ({cores} cores at {ghz:g} GHz): {pair_ms[0]:.0f}-{pair_ms[1]:.0f} ms per "
            f"pair on one core (budget {period_ms:.1f} ms per camera thread: it keeps "
            f"{kept[1]:.0f}-{kept[0]:.0f} fps per camera); "
            f"{need:.0f} images/s need {used[0]:.1f}-{used[1]:.1f} cores of {cores} "
            f"({100 * used[0] / cores:.0f}-{100 * used[1] / cores:.0f} %)"
        )


def cpu_mhz() -> float:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("cpu MHz"):
                return float(line.split(":")[1])
    except (OSError, ValueError):
        pass
    return 2600.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1 repeat of 1 s windows")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--window-s", type=float, default=3.0, help="per reference; agent 2x")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/egosurg_bench_encode"))
    parser.add_argument(
        "--x86-ghz",
        type=float,
        nargs=2,
        default=(round(cpu_mhz() / 1000, 2), 3.7),
        help="this core's effective clock, low high (default: /proc/cpuinfo's, Zen 4's boost)",
    )
    parser.add_argument(
        "--per-clock",
        type=float,
        nargs=2,
        default=(0.5, 0.9),
        help="an A78AE core's JPEG work per clock relative to this core, low high",
    )
    args = parser.parse_args(argv)
    repeat, window_s = (1, 1.0) if args.quick else (args.repeat, args.window_s)
    cv2.setNumThreads(1)  # imencode is single-threaded anyway; keep OpenCV's pool out of it
    pair = load_pair(args.cache)
    load0 = os.getloadavg()
    results = [one_repeat(pair, window_s) for _ in range(repeat)]
    load1 = os.getloadavg()
    print(
        f"HD1200 pair, JPEG quality {QUALITY}, {repeat} repeat(s) of {window_s:g} s windows "
        f"(agent {2 * window_s:g} s); cv2 {cv2.__version__}; {os.cpu_count()} CPUs; load "
        f"average {load0[0]:.1f} before, {load1[0]:.1f} after\n"
    )
    print_table([rows for rows, _ in results])
    print()
    print_agent([agent for _, agent in results])
    names = [r["name"] for r in results[0][0]]
    med = {
        n: statistics.median(rows[names.index(n)]["cpu_p50"] for rows, _ in results) for n in names
    }
    print_budget(
        med["encode_pair, 1 thread"], med["BGRA->BGR (ZED source)"], args.x86_ghz, args.per_clock
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
