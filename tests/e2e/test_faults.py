"""Fault injection on the deployed capture chain: real agent and recorder processes (sim/deploy.py's
SimRig, CURVE on), a real TCP proxy in one agent's frame link (tests/e2e/netproxy.py), real
filesystems filled or frozen (tmpfs, a loop-mounted ext4 and fsfreeze, as root), a real clock
step in one agent process (libfaketime). What an operator relies on: a fault costs exactly the
frames it touched, the gap is on record where it happened, the take goes on or stops cleanly with
the reason, and memory stays bounded.

tests/e2e/test_capture_integration.py already covers: a killed agent leaves a RECONNECT gap spanning
its death and spares the other node; a SIGKILLed recorder leaves a readable file; malformed
traffic is counted; the disk reserve stops a take before the disk fills."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zmq

from capture_agent.operator.control import format_status
from protocol.session import GapKind, SessionReader
from protocol.wire import ControlReply, ControlRequest
from sim.deploy import SimRig, SimRigSpec, free_ports, write_sim_rig
from tests.e2e.netproxy import TcpProxy

FPS = 15.0
PERIOD_NS = int(1e9 / FPS)
FAKETIME = Path("/usr/lib/x86_64-linux-gnu/faketime/libfaketime.so.1")
RSS_GROWTH_MB = 150  # a recorder or agent may grow this much during a fault (frames are ~0.1 MB)

pytestmark = pytest.mark.slow


# -- the rig ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Iterator[SimRig]:
    """The sim rig (two agents, two cameras each, no simulated drops, so every missing frame is
    the fault's), with orin-b's frame link through a proxy; ``rig.proxy``."""
    files = write_sim_rig(
        tmp_path_factory.mktemp("faults"),
        SimRigSpec(
            seed=3,
            fps=FPS,
            drop_probability=0.0,
            content_fps=0.5,
            prerender_s=2.0,
            plaintext=True,  # the capture path under test; sealed: test_sealed_session.py
        ),
    )
    node_b = files.node_configs["orin-b"].read_text()
    port_b = int(re.search(r'frames_bind = "tcp://127.0.0.1:(\d+)"', node_b).group(1))
    # orin-b's own buffering (its queue and its socket's high-water mark, 100 frames when the
    # queue is 8) must be shorter than the 10 s cut (300 frames): with the default 120-frame
    # queue (480 + 120 frames) a cut is absorbed whole and delivered late, so whether frames are
    # lost would depend on the kernel's TCP buffers, not on the fault
    node_b, n = re.subn(r"(?m)^queue_frames = \d+$", "queue_frames = 8", node_b)
    assert n == 1, "the deployed node.toml names queue_frames once"
    files.node_configs["orin-b"].write_text(node_b)
    proxy = TcpProxy(port_b)
    rig_text = files.rig_config.read_text()
    files.rig_config.write_text(
        rig_text.replace(f'frames = "tcp://127.0.0.1:{port_b}"', f'frames = "{proxy.address}"')
    )
    sim_rig = SimRig(files).start()
    sim_rig.proxy = proxy  # type: ignore[attr-defined]
    try:
        sim_rig.wait_streaming(timeout_s=300)
        yield sim_rig
    finally:
        sim_rig.close()
        proxy.close()


def _rss_mb(pid: int) -> float:
    text = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"VmRSS:\s+(\d+) kB", text).group(1)) / 1024


@contextmanager
def _peak_rss(pids: dict[str, int]) -> Iterator[dict[str, float]]:
    """The peak RSS (MB) of each process while the block runs, sampled every 0.2 s."""
    peak = {name: _rss_mb(pid) for name, pid in pids.items()}
    start = dict(peak)
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.2):
            for name, pid in pids.items():
                try:
                    peak[name] = max(peak[name], _rss_mb(pid))
                except (OSError, AttributeError):
                    pass

    t = threading.Thread(target=sample, daemon=True)
    t.start()
    try:
        yield {"start": start, "peak": peak}  # type: ignore[dict-item]
    finally:
        done.set()
        t.join()


def _tables(path: str) -> tuple[dict[int, dict[str, np.ndarray]], list, object, int]:
    with SessionReader(path) as r:
        tables = {s: r.frame_table(s) for s in r.info.camera_serials}
        return tables, r.gaps(), r.sets(), r.info.tolerance_ns


def _holes(table: dict[str, np.ndarray]) -> list[tuple[int, int]]:
    """(stamp before, stamp after) of every place where the camera's frame_index does not go up
    by exactly one: a frame of the camera is missing there (the rig's sim drops nothing)."""
    idx, stamps = table["frame_index"], table["capture_unix_ns"]
    jumps = np.flatnonzero(np.diff(idx) != 1)
    return [(int(stamps[k]), int(stamps[k + 1])) for k in jumps]


def _assert_gaps_are_the_holes(tables, gaps, serials) -> None:
    """Every hole in a camera's frames has a gap record with exactly its bounds, and no gap
    record of the camera (bar the node-level SEQ_GAP) is anywhere else."""
    for s in serials:
        holes = _holes(tables[s])
        records = {
            (g.start_unix_ns, g.end_unix_ns)
            for g in gaps
            if g.camera_serial == s and g.kind != GapKind.SEQ_GAP
        }
        assert set(holes) <= records, f"camera {s}: holes {holes} not all on record {records}"
        assert records <= set(holes), f"camera {s}: gap records {records} where no frame is lost"


def _assert_sets_sound(sets, tables, serials, tolerance_ns: int) -> None:
    """No set mixes frames more than half a period apart, no frame is in two sets, and set
    times increase."""
    assert np.all(np.diff(sets.set_unix_ns) > 0)
    for col, s in enumerate(serials):
        rows = sets.members[:, col]
        rows = rows[rows >= 0]
        assert len(rows) == len(set(rows.tolist())), f"camera {s}: a frame is in two sets"
    for k, members in enumerate(sets.members):
        stamps = [
            int(tables[s]["capture_unix_ns"][m])
            for s, m in zip(serials, members, strict=True)
            if m >= 0
        ]
        assert max(stamps) - min(stamps) <= tolerance_ns, f"set {k} mixes frames {stamps}"
        assert all(abs(t - int(sets.set_unix_ns[k])) <= tolerance_ns for t in stamps)


# -- an extra recorder on a chosen disk -------------------------------------------------------
def _control(rig: SimRig, url: str, verb: str, timeout_s: float = 5.0, **args) -> ControlReply:
    ctx = zmq.Context.instance()
    sock = rig.files.control_socket(ctx)
    sock.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
    try:
        sock.connect(url)
        sock.send(ControlRequest(verb=verb, args=args).to_bytes())
        return ControlReply.from_bytes(sock.recv())
    finally:
        sock.close(linger=0)


@contextmanager
def _recorder_on(
    rig: SimRig, output_dir: Path, name: str
) -> Iterator[tuple[subprocess.Popen, str]]:
    """A second ``egosurg recorder`` process of the same rig (same keys, same agents), writing
    to ``output_dir`` with no disk reserve; yields (process, control url) once it sees every
    camera streaming."""
    port = free_ports(1)[0]
    text = rig.files.rig_config.read_text()
    text = re.sub(r'control_bind = ".*"', f'control_bind = "tcp://127.0.0.1:{port}"', text)
    text = re.sub(r'output_dir = ".*"', f'output_dir = "{output_dir}"', text)
    text = re.sub(r"disk_reserve_gb = .*", "disk_reserve_gb = 0.0", text)
    config = rig.files.directory / f"{name}.toml"  # beside rig.toml: the key paths are relative
    config.write_text(text)
    url = f"tcp://127.0.0.1:{port}"
    log = open(rig.files.directory / "logs" / f"{name}.log", "ab")
    proc = subprocess.Popen(
        [sys.executable, "-m", "protocol.cli", "recorder", "--config", str(config)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, f"{name} exited; see {log.name}"
            assert time.monotonic() < deadline, f"{name} never saw every camera; see {log.name}"
            try:
                st = _control(rig, url, "status", timeout_s=2.0)
                if st.ok and all(c["streaming"] for c in st.result["cameras"]):
                    break
            except zmq.Again:
                pass
            time.sleep(0.5)
        yield proc, url
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        log.close()


# -- the faults ---------------------------------------------------------------------------------
def test_an_agent_killed_mid_take_costs_exactly_its_dead_interval(rig):
    """SIGKILL orin-a, restart it: the take goes on; its cameras' gaps are on record with the
    bounds of the frames around them, and no other frame of any camera is lost."""
    started = rig.control("start", case="agent-kill")
    time.sleep(2.0)
    rig.signal("agent-orin-a", signal.SIGKILL)
    time.sleep(3.0)  # past the recorder's live window: wait_streaming waits for the new agent
    assert rig.control("status")["recording"], "the take stopped when an agent died"
    rig.start_agent("orin-a")
    rig.wait_streaming(timeout_s=120)
    time.sleep(2.0)
    summary = rig.control("stop")
    assert summary["file"] == started["file"]
    tables, gaps, sets, tolerance = _tables(summary["file"])
    serials = list(tables)
    a = set(rig.files.serials_by_node["orin-a"])
    for s in serials:
        holes = _holes(tables[s])
        if s in a:
            assert len(holes) == 1, f"camera {s}: one outage expected, found {holes}"
            assert holes[0][1] - holes[0][0] > 1e9  # the agent was dead for over a second
        else:
            assert holes == [], f"camera {s} on the healthy node lost frames at {holes}"
    _assert_gaps_are_the_holes(tables, gaps, serials)
    _assert_sets_sound(sets, tables, serials, tolerance)


def test_an_agent_cut_off_for_ten_seconds_leaves_its_exact_gap_and_bounded_memory(rig):
    """orin-b's link stops moving bytes for 10 s (a pulled cable): the recording goes on with
    orin-a, the recorder's and the agent's memory stay bounded, orin-b's missing frames lie in
    the cut and are on record with their exact bounds, and orin-b is recorded again after."""
    cut_s = 10.0
    pids = {"recorder": rig.procs["recorder"].pid, "agent": rig.procs["agent-orin-b"].pid}
    rig.control("start", case="net-cut")
    time.sleep(2.0)
    with _peak_rss(pids) as rss:
        cut_at = time.time_ns()
        rig.proxy.pause()
        time.sleep(cut_s)
        rig.proxy.resume()
        resumed_at = time.time_ns()
        time.sleep(4.0)
        assert rig.control("status")["recording"]
    summary = rig.control("stop")
    for name in pids:
        grew = rss["peak"][name] - rss["start"][name]
        assert grew < RSS_GROWTH_MB, f"{name} grew {grew:.0f} MB during the cut"
    tables, gaps, sets, tolerance = _tables(summary["file"])
    serials = list(tables)
    b = set(rig.files.serials_by_node["orin-b"])
    for s in serials:
        holes = _holes(tables[s])
        if s not in b:
            assert holes == [], f"camera {s} on the connected node lost frames at {holes}"
            continue
        assert holes, f"camera {s}: 10 s cut off, yet no frame is missing"
        for before, after in holes:  # what is missing was captured during the cut
            assert before >= cut_at - 2 * PERIOD_NS and after <= resumed_at + 8e9
        assert tables[s]["capture_unix_ns"][-1] > resumed_at  # recorded again after the cut
    _assert_gaps_are_the_holes(tables, gaps, serials)
    _assert_sets_sound(sets, tables, serials, tolerance)


@contextmanager
def _mounted(mount: Path, source: list[str], what: str, *, thaw: bool = False) -> Iterator[Path]:
    """``mount <source...> <mount>`` for the test, unmounted lazily after it (thawed first where
    the test may have frozen it); the test is skipped where this user cannot mount ``what``."""
    mount.mkdir()
    done = subprocess.run(["mount", *source, str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount {what} (needs root): {done.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        if thaw:
            subprocess.run(["fsfreeze", "-u", str(mount)], capture_output=True)
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.fixture
def tmpfs(tmp_path) -> Iterator[Path]:
    with _mounted(tmp_path / "tmpfs", ["-t", "tmpfs", "-o", "size=200m", "tmpfs"], "a tmpfs") as m:
        yield m


def test_a_disk_filled_by_another_writer_stops_the_take_cleanly(rig, tmpfs):
    """Another process fills the disk at once (faster than the reserve check can see it
    coming): the take stops with the reason, the recorder goes on, the file is readable, and
    memory stays bounded."""
    sessions = tmpfs / "sessions"
    with _recorder_on(rig, sessions, "recorder-full") as (proc, url):
        reply = _control(rig, url, "start", case="disk-full", planned_duration_min=0.001)
        assert reply.ok, reply.error
        time.sleep(2.0)
        with _peak_rss({"recorder": proc.pid}) as rss:
            filler = tmpfs / "filler"
            with open(filler, "wb") as f:  # fill every free byte
                chunk = b"\0" * (1 << 20)
                try:
                    while True:
                        f.write(chunk)
                        f.flush()
                except OSError:
                    pass
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                st = _control(rig, url, "status")
                assert st.ok, st.error
                if not st.result["recording"]:
                    break
                time.sleep(0.5)
        assert proc.poll() is None, "the recorder exited on a full disk"
        assert not st.result["recording"], "the take went on writing into a full disk"
        reason = st.result["last_recording"]["reason"]
        assert re.search(r"disk|space|reserve|fail", reason), reason
        grew = rss["peak"]["recorder"] - rss["start"]["recorder"]
        assert grew < RSS_GROWTH_MB, f"the recorder grew {grew:.0f} MB on a full disk"
        filler.unlink()  # room for the reader's own needs
        with SessionReader(reply.result["file"]) as r:
            assert not [p for p in r.verify() if p.startswith("error")]
            assert r.frame_count(r.info.camera_serials[0]) > 5


@pytest.fixture
def freezable_disk(tmp_path) -> Iterator[Path]:
    """An ext4 filesystem on a loop device, which ``fsfreeze`` can stall (writes block)."""
    if not shutil.which("fsfreeze") or not shutil.which("mkfs.ext4"):
        pytest.skip("needs fsfreeze and mkfs.ext4 (util-linux, e2fsprogs)")
    image = tmp_path / "disk.img"
    subprocess.run(["truncate", "-s", "400M", str(image)], check=True)
    subprocess.run(["mkfs.ext4", "-q", "-F", str(image)], check=True)
    loop = ["-o", "loop", str(image)]
    with _mounted(tmp_path / "ext4", loop, "a loop-mounted filesystem", thaw=True) as m:
        yield m


def test_a_stalling_disk_is_reported_and_the_take_resumes(rig, freezable_disk):
    """The session's filesystem is frozen for 8 s (every write blocks, as on a stalling disk):
    the recorder still answers and reports the stall, its memory stays bounded, and after the
    disk comes back the same take goes on and the file holds frames from after the stall."""
    stall_s = 8.0
    with _recorder_on(rig, freezable_disk / "sessions", "recorder-stall") as (proc, url):
        reply = _control(rig, url, "start", case="disk-stall", planned_duration_min=0.001)
        assert reply.ok, reply.error
        time.sleep(2.0)
        answers = []
        with _peak_rss({"recorder": proc.pid}) as rss:
            subprocess.run(["fsfreeze", "-f", str(freezable_disk)], check=True)
            # whatever happens below, the disk comes back: a frozen fs would hang the machine's
            # other writers
            thaw = threading.Timer(
                stall_s, subprocess.run, (["fsfreeze", "-u", str(freezable_disk)],)
            )
            thaw.start()
            try:
                time.sleep(stall_s / 2)
                try:
                    answers.append(_control(rig, url, "status", timeout_s=2.0))
                except zmq.Again:
                    answers.append(None)
            finally:
                thaw.join()
            thawed_at = time.time_ns()
            time.sleep(4.0)
        grew = rss["peak"]["recorder"] - rss["start"]["recorder"]
        assert grew < RSS_GROWTH_MB, f"the recorder grew {grew:.0f} MB while the disk stalled"
        log = rig.files.directory / "logs" / "recorder-stall.log"
        assert proc.poll() is None, (
            f"the recorder died (exit {proc.returncode}) after its disk stalled: "
            f"{log.read_text().strip().splitlines()[-1]}"
        )
        assert answers[0] is not None, "the recorder did not answer status while its disk stalled"
        after = _control(rig, url, "status")
        assert after.ok
        assert after.result["recording"], "the take ended on a disk stall"
        summary = _control(rig, url, "stop", timeout_s=30)
        assert summary.ok, summary.error
        with SessionReader(summary.result["file"]) as r:
            last = max(int(r.frame_table(s)["capture_unix_ns"][-1]) for s in r.info.camera_serials)
        assert last > thawed_at, "nothing was written after the disk came back"
        during = answers[0]
        assert re.search(r"stall|progress|write", str(during.result)), during.result
        # what 'egosurg status' printed meanwhile: the stall, and the take still recording
        assert during.result["recording"] and during.result["write_stalled_s"] > 0, during.result
        assert "WRITING STALLED" in format_status(during.result)


def test_a_clock_step_on_one_node_is_flagged_and_no_set_mixes_times(rig):
    """orin-b's clock (its agent process's, through libfaketime) steps 1.5 s forward mid-take:
    the step is on record as a gap for its cameras, and no set groups frames more than half a
    period apart."""
    if not FAKETIME.exists():
        pytest.skip(f"needs libfaketime ({FAKETIME}; Debian package libfaketime)")
    offset_file = rig.files.directory / "orin-b.faketime"
    offset_file.write_text("+0\n")
    rig.signal("agent-orin-b", signal.SIGTERM)
    time.sleep(3.0)  # past the recorder's live window: wait_streaming waits for the new agent
    fake = {
        "LD_PRELOAD": str(FAKETIME),
        "FAKETIME_TIMESTAMP_FILE": str(offset_file),
        "FAKETIME_CACHE_DURATION": "1",  # re-read the offset every second
        # FAKETIME_DONT_FAKE_MONOTONIC=1 would be truer to a PTP step, but then Python's
        # time.sleep fails with EINVAL under libfaketime 0.9.10; the monotonic clock steps too,
        # by less than the agent's 2 s watchdog
    }
    old = {k: os.environ.get(k) for k in fake}
    os.environ.update(fake)  # SimRig passes its environment to the agent it starts
    try:
        rig.start_agent("orin-b")
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    rig.wait_streaming(timeout_s=120)
    rig.control("start", case="clock-step")
    time.sleep(3.0)
    offset_file.write_text("+1.5\n")
    stepped_at = time.time_ns()
    time.sleep(5.0)
    summary = rig.control("stop")
    tables, gaps, sets, tolerance = _tables(summary["file"])
    serials = list(tables)
    for s in rig.files.serials_by_node["orin-b"]:
        steps = np.diff(tables[s]["capture_unix_ns"])
        assert steps.max() > 1.0e9, f"camera {s}: its stamps never jumped; the clock did not step"
        flagged = [g for g in gaps if g.camera_serial == s and g.end_unix_ns > stepped_at]
        assert flagged, f"camera {s}: its 1.5 s clock step is not on record"
    _assert_sets_sound(sets, tables, serials, tolerance)
