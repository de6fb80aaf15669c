"""One recording of bench_capture.py: start the publishers and the recorder, record, stop, and
read the numbers (``run_recording``); and the real JPEG pairs a session holds."""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import subprocess
import time
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
    from sim.deploy import SimRig, SimRigError

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
    rig = SimRig(files)
    spy: subprocess.Popen | None = None
    feeder_reports: list[dict] = []
    try:
        rig.start()  # the agents (none for replay) and the recorder
        if feed == "replay":
            for node, (fr, ct) in endpoints.items():
                p = ctx.Process(
                    target=feeder,
                    args=(
                        node,
                        fr,
                        ct,
                        list(files.serials_by_node[node]),
                        fps,
                        pairs,
                        time.monotonic() + duration_s + 300.0,
                        stop_event,
                        q,
                        None if insecure else str(files.directory / "keys" / f"{node}.key_secret"),
                    ),
                    daemon=True,
                )
                p.start()
                feeders.append(p)
        wait_deadline = time.monotonic() + 600.0
        while True:  # SimRig.wait_streaming, in short slices so a dead feeder is seen at once
            if any(not p.is_alive() for p in feeders):
                raise RuntimeError("a replay feeder exited before streaming")
            try:
                rig.wait_streaming(timeout_s=3.0)
                break
            except SimRigError:
                if time.monotonic() > wait_deadline:
                    raise
        time.sleep(2.0)  # let every publisher settle after the last camera came up
        rec = rig.procs["recorder"]
        pubs = [p.pid for n, p in rig.procs.items() if n.startswith("agent-")]
        pubs += [p.pid for p in feeders]
        cpu0 = cpu_seconds(rec.pid), sum(cpu_seconds(p) for p in pubs)
        sched0, busy0 = thread_schedstat(rec.pid), machine_busy_seconds()
        t0 = time.monotonic()
        started = rig.control("start", timeout_s=30.0, case=name.replace(" ", "-"))
        if profile:
            exe = py_spy_available()
            if exe is None:
                log("py-spy not found: profile skipped (.venv/bin/pip install py-spy)")
            else:
                spy = subprocess.Popen(
                    [
                        exe,
                        "record",
                        "--pid",
                        str(rec.pid),
                        "--duration",
                        str(max(1, int(duration_s) - 1)),
                        "--rate",
                        "100",
                        "--format",
                        "raw",
                        "--nonblocking",
                        "--threads",
                        "--output",
                        str(directory / "recorder.pyspy.txt"),
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
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
                break
            time.sleep(max(0.0, min(1.0, deadline - now, (poll_at or [deadline])[0] - now)))
        cpu1 = cpu_seconds(rec.pid), sum(cpu_seconds(p) for p in pubs)
        sched1, busy1 = thread_schedstat(rec.pid), machine_busy_seconds()
        names1 = thread_names(rec.pid)
        wall = time.monotonic() - t0
        summary = rig.control("stop", timeout_s=180.0)
        stop_event.set()
        for _ in feeders:
            feeder_reports.append(q.get(timeout=30))
        profile_text = ""
        if spy is not None:
            try:
                spy.wait(timeout=60)
            except subprocess.TimeoutExpired:
                spy.kill()
                spy.wait(timeout=10)
            profile_text = summarize_py_spy(directory / "recorder.pyspy.txt")
    finally:
        stop_event.set()
        if spy is not None and spy.poll() is None:
            spy.kill()
            spy.wait(timeout=10)
        rig.close()
        for p in feeders:
            p.join(timeout=10)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5)
    cams = summary["cameras"].values()
    (ta, fa), (tb, fb) = polls
    result = RunResult(
        name=name,
        feed=feed,
        cameras=cameras,
        fps=fps,
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
        recorder_cpu=100.0 * (cpu1[0] - cpu0[0]) / wall,
        feeders_cpu=100.0 * (cpu1[1] - cpu0[1]) / wall,
        io_thread_run=io_thread(sched0, sched1, names1, wall)[0],
        io_thread_wait=io_thread(sched0, sched1, names1, wall)[1],
        threads=threads_running(sched0, sched1, names1, wall),
        other_cpu=100.0 * ((busy1 - busy0) - (cpu1[0] - cpu0[0]) - (cpu1[1] - cpu0[1])) / wall,
        steady_rate=(fb - fa) / (tb - ta),
        feeder_lag_ms=max((r["max_lag_ms"] for r in feeder_reports), default=None),
        profile=profile_text,
        insecure=insecure,
    )
    session = Path(started["file"])
    if payload_out is not None:
        payload_out.extend(read_pairs(session))
    if not keep:
        session.unlink(missing_ok=True)  # its dirty pages are dropped, not written
    log(
        f"{name}: {result.frames} frames, steady {result.steady_rate:.1f}/s of "
        f"{result.offered_rate:g} offered, lost {result.lost}, recorder CPU "
        f"{result.recorder_cpu:.0f}% (I/O thread runs {result.io_thread_run:.0f}%, waits "
        f"{result.io_thread_wait:.0f}%), publishers {result.feeders_cpu:.0f}%, others "
        f"{result.other_cpu:.0f}%, recorder threads: {result.threads}, p99 "
        f"{result.latency_ms.get('p99')} ms"
        + (f", feeder lag {result.feeder_lag_ms:.1f} ms" if feed == "replay" else "")
    )
    return result


def read_pairs(session: Path, per_camera: int = 2) -> list[tuple[bytes, bytes]]:
    """A few real (left, right) JPEG pairs per camera from a session file."""
    from protocol.session import SessionReader

    pairs = []
    with SessionReader(session) as r:
        for serial in r.info.camera_serials:
            n = r.frame_count(serial)
            for row in range(min(per_camera, n)):
                pairs.append(r.frame_bytes(serial, (row * 7) % n))
    return pairs
