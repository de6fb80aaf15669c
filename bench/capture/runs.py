"""One recording of bench_capture.py: start the publishers and the recorder, record, stop, and
read the numbers (``run_recording``); and the real JPEG pairs a session holds."""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from bench.capture.measure import (
    RESOLUTION,
    RunResult,
    cpu_seconds,
    io_thread,
    log,
    machine_busy_seconds,
    py_spy_available,
    summarize_py_spy,
    thread_names,
    thread_schedstat,
    threads_running,
    wait_quiet,
)
from bench.capture.rigs import feeder, make_replay_rig, make_rig


@dataclass(frozen=True)
class _Counters:
    """CPU counters read at one end of the measured window."""

    recorder_cpu_s: float
    publishers_cpu_s: float
    recorder_threads: dict[int, tuple[int, int]]  # thread_schedstat of the recorder
    machine_busy_s: float


def _counters(recorder_pid: int, publisher_pids: list[int]) -> _Counters:
    return _Counters(
        recorder_cpu_s=cpu_seconds(recorder_pid),
        publishers_cpu_s=sum(cpu_seconds(p) for p in publisher_pids),
        recorder_threads=thread_schedstat(recorder_pid),
        machine_busy_s=machine_busy_seconds(),
    )


def run_recording(
    directory: Path,
    name: str,
    cameras: int,
    fps: float,
    duration_s: float,
    *,
    feed: str = "agents",
    pairs: list | None = None,
    keep: bool,
    profile: bool = False,
    payload_out: list | None = None,
    insecure: bool = False,
) -> RunResult:
    """Start the publishers and the recorder, record ``duration_s``, stop, read the numbers."""
    from sim.deploy import SimRig

    if directory.exists():
        shutil.rmtree(directory)
    # Start from clean page cache: dirty pages an earlier run left would be written back (and
    # throttle writers) during this one.
    os.sync()
    wait_quiet(name)
    ctx = mp.get_context("spawn")
    feeders: list = []
    stop_event = ctx.Event()
    q = ctx.Queue()
    files, endpoints = _rig_files(directory, name, feed, cameras, fps, duration_s, insecure)
    rig = SimRig(files)
    spy: subprocess.Popen | None = None
    feeder_reports: list[dict] = []
    profile_path = directory / "recorder.pyspy.txt"
    try:
        rig.start()  # the agents (none for replay) and the recorder
        if feed == "replay":
            stop_at = time.monotonic() + duration_s + 300.0
            for node, (fr, ct) in endpoints.items():
                key = None if insecure else str(files.directory / "keys" / f"{node}.key_secret")
                serials = list(files.serials_by_node[node])
                args = (node, fr, ct, serials, fps, pairs, stop_at, stop_event, q, key)
                p = ctx.Process(target=feeder, args=args, daemon=True)
                p.start()
                feeders.append(p)  # the finally joins the feeders started
        _wait_streaming(rig, feeders)
        time.sleep(2.0)  # let every publisher settle after the last camera came up
        rec = rig.procs["recorder"]
        pubs = [p.pid for n, p in rig.procs.items() if n.startswith("agent-")]
        pubs += [p.pid for p in feeders]
        before = _counters(rec.pid, pubs)
        t0 = time.monotonic()
        started = rig.control("start", timeout_s=30.0, case=name.replace(" ", "-"))
        if profile:
            spy = _start_py_spy(rec.pid, duration_s, profile_path)
        polls = _record(rig, feeders, t0, duration_s)
        after = _counters(rec.pid, pubs)
        names = thread_names(rec.pid)
        wall = time.monotonic() - t0
        summary = rig.control("stop", timeout_s=180.0)
        stop_event.set()
        for _ in feeders:
            feeder_reports.append(q.get(timeout=30))
        profile_text = "" if spy is None else _finish_py_spy(spy, profile_path)
    finally:
        stop_event.set()
        _stop_all(spy, rig, feeders)
    (ta, fa), (tb, fb) = polls
    result = _run_result(
        summary,
        name=name,
        feed=feed,
        cameras=cameras,
        fps=fps,
        cpu=(before, after, names, wall),
        steady_rate=(fb - fa) / (tb - ta),
        feeder_lag_ms=max((r["max_lag_ms"] for r in feeder_reports), default=None),
        profile=profile_text,
        insecure=insecure,
    )
    session = Path(started["file"])
    if payload_out is not None:
        payload_out.extend(read_pairs(session, files.identity))
    if not keep:
        session.unlink(missing_ok=True)  # its dirty pages are dropped, not written
    _log_result(result)
    return result


def _rig_files(
    directory: Path,
    name: str,
    feed: str,
    cameras: int,
    fps: float,
    duration_s: float,
    insecure: bool,
) -> tuple:
    """The rig's files, and the replay feeders' (frames, control) endpoints by node ({} for
    the sim agents)."""
    endpoints: dict[str, tuple[str, str]] = {}
    if feed == "agents":
        files = make_rig(directory, cameras, fps, duration_s, insecure=insecure)
        what = "2 agents"
    else:
        files, endpoints = make_replay_rig(directory, cameras, fps, duration_s, insecure)
        what = "2 replay feeders"
    log(
        f"{name}: starting {what} ({cameras} cameras at {fps:g} fps, {RESOLUTION}) + recorder, "
        + ("PLAINTEXT links" if insecure else "CURVE links")
    )
    return files, endpoints


def _stop_all(spy: subprocess.Popen | None, rig, feeders: list) -> None:
    """Whatever is still running of the run: py-spy, the rig, the feeders."""
    if spy is not None and spy.poll() is None:
        spy.kill()
        spy.wait(timeout=10)
    rig.close()
    for p in feeders:
        p.join(timeout=10)
        if p.is_alive():
            p.terminate()
            p.join(timeout=5)


def _wait_streaming(rig, feeders: list) -> None:
    """SimRig.wait_streaming, in short slices so a dead feeder is seen at once."""
    from sim.deploy import SimRigError

    wait_deadline = time.monotonic() + 600.0
    while True:
        if any(not p.is_alive() for p in feeders):
            raise RuntimeError("a replay feeder exited before streaming")
        try:
            rig.wait_streaming(timeout_s=3.0)
            return
        except SimRigError:
            if time.monotonic() > wait_deadline:
                raise


def _start_py_spy(pid: int, duration_s: float, output: Path) -> subprocess.Popen | None:
    """py-spy sampling the recorder for the recording (None, with a log line, without py-spy)."""
    exe = py_spy_available()
    if exe is None:
        log("py-spy not found: profile skipped (.venv/bin/pip install py-spy)")
        return None
    return subprocess.Popen(
        [
            exe,
            "record",
            "--pid",
            str(pid),
            "--duration",
            str(max(1, int(duration_s) - 1)),
            "--rate",
            "100",
            "--format",
            "raw",
            "--nonblocking",
            "--threads",
            "--output",
            str(output),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _finish_py_spy(spy: subprocess.Popen, output: Path) -> str:
    """Wait for py-spy to write its profile, and summarize it."""
    try:
        spy.wait(timeout=60)
    except subprocess.TimeoutExpired:
        spy.kill()
        spy.wait(timeout=10)
    return summarize_py_spy(output)


def _record(rig, feeders: list, t0: float, duration_s: float) -> list[tuple[float, int]]:
    """Watch the processes until ``t0 + duration_s``; the recorder's frame count at a quarter
    of the way (at least 2 s in) and at the end, as (monotonic s, frames), for the steady
    rate."""
    polls: list[tuple[float, int]] = []
    poll_at = [t0 + max(2.0, 0.25 * duration_s), t0 + duration_s]
    deadline = t0 + duration_s
    while True:
        for pname, proc in rig.procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"{pname} exited during the recording; see {rig.logs}")
        if any(not p.is_alive() for p in feeders):
            raise RuntimeError("a replay feeder exited during the recording")
        now = time.monotonic()
        if poll_at and now >= poll_at[0]:
            poll_at.pop(0)
            a = time.monotonic()
            st = rig.control("status", timeout_s=60.0)
            polls.append(((a + time.monotonic()) / 2, int(st["frames"])))
            continue
        if now >= deadline:
            return polls
        time.sleep(max(0.0, min(1.0, deadline - now, (poll_at or [deadline])[0] - now)))


def _run_result(
    summary: dict,
    *,
    cpu: tuple[_Counters, _Counters, dict[int, str], float],
    **fields,
) -> RunResult:
    """The numbers of one run: the recorder's stop summary, the CPU shares over the measured
    window (``cpu``: counters before and after, the recorder's thread names, the wall
    seconds), and ``fields`` (the run's name and settings, its rate and profile)."""
    before, after, names, wall = cpu
    sched0, sched1 = before.recorder_threads, after.recorder_threads
    recorder_cpu_s = after.recorder_cpu_s - before.recorder_cpu_s
    publishers_cpu_s = after.publishers_cpu_s - before.publishers_cpu_s
    busy_s = after.machine_busy_s - before.machine_busy_s
    cams = summary["cameras"].values()
    return RunResult(
        duration_s=float(summary["duration_s"]),
        frames=int(summary["frames"]),
        sets=int(summary["sets"]),
        bytes=int(summary["bytes"]),
        dropped=sum(int(c["dropped"]) for c in cams),
        transport_lost=sum(int(c["transport_lost"]) for c in cams),
        not_written=int(summary.get("frames_not_written_at_stop", 0))
        + int(summary.get("frames_not_written_write_failed", 0))
        + int(summary.get("frames_not_written_disk_stalled", 0)),
        latency_ms=summary["capture_to_durable_ms"],
        recorder_cpu=100.0 * recorder_cpu_s / wall,
        feeders_cpu=100.0 * publishers_cpu_s / wall,
        io_thread_run=io_thread(sched0, sched1, names, wall)[0],
        io_thread_wait=io_thread(sched0, sched1, names, wall)[1],
        threads=threads_running(sched0, sched1, names, wall),
        other_cpu=100.0 * (busy_s - recorder_cpu_s - publishers_cpu_s) / wall,
        **fields,
    )


def _log_result(result: RunResult) -> None:
    log(
        f"{result.name}: {result.frames} frames, steady {result.steady_rate:.1f}/s of "
        f"{result.offered_rate:g} offered, lost {result.lost}, recorder CPU "
        f"{result.recorder_cpu:.0f}% (I/O thread runs {result.io_thread_run:.0f}%, waits "
        f"{result.io_thread_wait:.0f}%), publishers {result.feeders_cpu:.0f}%, others "
        f"{result.other_cpu:.0f}%, recorder threads: {result.threads}, p99 "
        f"{result.latency_ms.get('p99')} ms"
        + (f", feeder lag {result.feeder_lag_ms:.1f} ms" if result.feed == "replay" else "")
    )


def read_pairs(
    session: Path, identity_path: Path | None, per_camera: int = 2
) -> list[tuple[bytes, bytes]]:
    """A few real (left, right) JPEG pairs per camera from a session file (opened with the rig's
    site identity when it is sealed)."""
    from protocol.sealing import load_identity
    from protocol.session import SessionReader

    identity = load_identity(identity_path) if identity_path is not None else None
    pairs = []
    with SessionReader(session, identity=identity) as r:
        for serial in r.info.camera_serials:
            n = r.frame_count(serial)
            for row in range(min(per_camera, n)):
                pairs.append(r.frame_bytes(serial, (row * 7) % n))
    return pairs
