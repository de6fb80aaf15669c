"""Measuring one run of bench_capture.py: its constants, the machine's and each process's CPU
from /proc, the recorder's threads, the result of one recording, py-spy's summary, and the
markdown table every section prints."""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import re
import shutil
import sys
import time
from pathlib import Path

RIG_CAMERAS, RIG_FPS = 4, 30.0
RESOLUTION = "HD1200"
MAX_FPS = 60.0  # the ZED X at HD1200
REPLAY_FPS = 120.0  # the most rig.toml allows
JPEG_QUALITY = 85  # SimRigSpec's default: about 280 kB per HD1200 image
SUSTAIN_RATE = 0.99  # stored rate over offered rate, measured inside the recording
REPLAY_SERIAL0 = 90_000_000
BUSY_OTHER_CPU = 50.0  # % of one core used by the rest of the machine: the step is run again
CLK_TCK = os.sysconf("SC_CLK_TCK")


def pair_header(node_id: str, serial: int, left: bytes, right: bytes, *, ptp_locked: bool) -> bytes:
    """The frame header of the HD1200 JPEG pair ``left``, ``right``, its index, seq and times 0:
    a sender stamps its own into a copy before each send."""
    from protocol.wire import FrameMessage

    return FrameMessage(
        node_id=node_id,
        camera_serial=serial,
        frame_index=0,
        seq=0,
        capture_unix_ns=0,
        host_receive_unix_ns=0,
        ptp_offset_ns=0,
        ptp_locked=ptp_locked,
        encoding="jpeg",
        width=1920,
        height=1200,
        left=left,
        right=right,
    ).header()


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), in seconds."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # fields 14 and 15 of proc(5)


def machine_busy_seconds() -> float:
    """CPU time all processes of the machine used so far (every core), in seconds."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    idle = v[3] + (v[4] if len(v) > 4 else 0)  # idle + iowait
    return (sum(v[:8]) - idle) / CLK_TCK  # user nice system idle iowait irq softirq steal


QUIET_WAIT_S = [120.0]  # set from --quiet-wait-s


def wait_quiet(what: str, threshold: float = 25.0) -> float:
    """Before a measurement, wait (at most QUIET_WAIT_S) until the rest of the machine uses
    under ``threshold`` % of a core over 2 s: this machine is shared, and the measurements
    assume the 2 cores are ours. Returns the last reading."""
    deadline = time.monotonic() + QUIET_WAIT_S[0]
    while True:
        b0, t0 = machine_busy_seconds(), time.monotonic()
        time.sleep(2.0)
        other = 100.0 * (machine_busy_seconds() - b0) / (time.monotonic() - t0)
        if other < threshold or time.monotonic() > deadline:
            if other >= threshold:
                log(f"{what}: the machine is still busy ({other:.0f}% of a core); going ahead")
            return other
        log(f"{what}: other processes use {other:.0f}% of a core; waiting for a quieter machine")
        time.sleep(10.0)


def thread_schedstat(pid: int) -> dict[int, tuple[int, int]]:
    """Per thread: (ns running on a CPU, ns runnable but waiting for one), from schedstat."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                run_ns, wait_ns, _ = (int(x) for x in f.read().split())
        except (OSError, ValueError):
            continue
        out[int(tid)] = (run_ns, wait_ns)
    return out


def thread_names(pid: int) -> dict[int, str]:
    """Per thread: its OS name (``comm``: libzmq names its threads, EgoSurg its writer)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                out[int(tid)] = f.read().strip()
        except OSError:
            continue
    return out


def threads_running(before: dict, after: dict, names: dict, wall_s: float) -> str:
    """The threads that ran more than 1% of the time, busiest first: "name 45%, ..."."""
    # a thread started since ``before`` (the session's writer) ran from 0
    run = {t: 100.0 * (after[t][0] - before.get(t, (0, 0))[0]) / 1e9 / wall_s for t in after}
    busy = sorted((pct, names.get(t, str(t))) for t, pct in run.items() if pct >= 1.0)
    return ", ".join(f"{name} {pct:.0f}%" for pct, name in reversed(busy))


def io_thread(before: dict, after: dict, names: dict, wall_s: float) -> tuple[float, float]:
    """(% running, % waiting for a CPU) of the recorder's I/O thread ("recorder-io"; the
    busiest thread for a recorder that does not name its threads) between two snapshots. The
    rest of the wall time it slept (idle, or blocked in I/O)."""
    deltas = {
        t: (after[t][0] - before[t][0], after[t][1] - before[t][1]) for t in after if t in before
    }
    named = [d for t, d in deltas.items() if names.get(t) == "recorder-io"]
    run, wait = named[0] if named else max(deltas.values(), default=(0, 0))
    return 100.0 * run / 1e9 / wall_s, 100.0 * wait / 1e9 / wall_s


def fmt(x: float | None, spec: str = ".0f") -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def table(header: list[str], rows: list[list[str]], right: set[int] | None = None) -> str:
    right = set(range(1, len(header))) if right is None else right
    out = ["| " + " | ".join(header) + " |"]
    out.append("|" + "|".join("---:" if i in right else "---" for i in range(len(header))) + "|")
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


@dataclasses.dataclass
class RunResult:
    name: str
    feed: str  # "agents" (egosurg agent + sim source) or "replay" (bench feeders)
    cameras: int
    fps: float
    duration_s: float
    frames: int
    sets: int
    bytes: int
    dropped: int
    transport_lost: int
    not_written: int  # frames of the take still queued at the stop and not written (counted)
    latency_ms: dict[str, float | None]
    recorder_cpu: float  # % of one core
    feeders_cpu: float  # % of one core, both publishers together
    steady_rate: float  # stereo frames/s stored between two status polls inside the recording
    io_thread_run: float  # % of wall time the recorder's busiest thread ran on a CPU
    io_thread_wait: float  # % of wall time it was runnable but waited for a CPU
    threads: str  # the recorder's threads and the % of wall time each ran
    other_cpu: float  # % of one core used by every other process of the machine
    feeder_lag_ms: float | None = None  # replay only: how late the feeders sent, at worst
    profile: str = ""
    insecure: bool = False  # plaintext links (the CURVE comparison), else CURVE

    @property
    def lost(self) -> int:
        return self.dropped + self.transport_lost + self.not_written

    @property
    def offered_rate(self) -> float:
        return self.cameras * self.fps

    @property
    def received_rate(self) -> float:
        return self.frames / self.duration_s

    @property
    def sustained(self) -> bool:
        return self.lost == 0 and self.steady_rate >= SUSTAIN_RATE * self.offered_rate


def py_spy_available() -> str | None:
    exe = Path(sys.executable).with_name("py-spy")
    if exe.exists():
        return str(exe)
    return shutil.which("py-spy")


def summarize_py_spy(path: Path, top: int = 12) -> str:
    """Where the recorder's threads spend their samples, from py-spy's collapsed stacks."""
    if not path.exists():
        return "(py-spy wrote no profile)"
    total = 0
    self_count: collections.Counter[str] = collections.Counter()
    incl: collections.Counter[str] = collections.Counter()
    threads: collections.Counter[str] = collections.Counter()
    for line in path.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if not stack or not n.isdigit():
            continue
        count = int(n)
        frames = stack.split(";")
        thread = frames[0] if frames[0].startswith(("thread", "process")) else "?"
        body = frames[1:] if thread != "?" else frames
        if body and body[0].startswith("process"):
            body = body[1:]
        total += count
        threads[re.sub(r" \(0x[0-9a-f]+\)", "", thread)] += count
        names = [re.sub(r" \(([^:]*/)?([^/:]+):\d+\)$", r" (\2)", f) for f in body]
        if names:
            self_count[names[-1]] += count
        for fname in set(names):
            incl[fname] += count
    if total == 0:
        return "(empty profile)"
    lines = [
        f"py-spy: {total} samples at 100 Hz (non-idle stacks), by thread: "
        + ", ".join(f"{t} {100 * c / total:.0f}%" for t, c in threads.most_common(4))
    ]
    lines.append("")
    lines.append(
        table(
            ["function (self time: the innermost frame)", "% of samples"],
            [[f"`{f}`", f"{100 * c / total:.1f}"] for f, c in self_count.most_common(top)],
        )
    )
    lines.append("")
    keep = [
        (f, c)
        for f, c in incl.most_common()
        if any(
            k in f
            for k in (
                "recorder.py",  # capture_agent/recorder/: the loop and its parts
                "intake.py",
                "recording.py",
                "write_queue.py",
                "write.py",  # protocol/session/: the writer, its datasets and chunk sink
                "datasets.py",
                "chunk_sink.py",
                "sync.py",
                "accounting.py",
                "messages.py",
                "frame.py",  # protocol/wire/: the messages' code since the split
                "status.py",
                "checks.py",
                "socket.py",
                "h5py",
                "dataset.py",
            )
        )
    ][:top]
    lines.append(
        table(
            ["function (inclusive: anywhere on the stack)", "% of samples"],
            [[f"`{f}`", f"{100 * c / total:.1f}"] for f, c in keep],
        )
    )
    return "\n".join(lines)
