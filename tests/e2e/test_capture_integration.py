"""The capture chain as deployed: two simulated Jetson agents and the recorder as separate
processes on loopback TCP, checked against the simulator's ground truth. Also the faults a
hospital recording system must survive: killed agents, a killed recorder, malformed traffic,
refused starts, a filling disk and racing operators."""

from __future__ import annotations

import shutil
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
import zmq
import zmq.auth

from capture_agent.errors import CommandRefusedError
from capture_agent.operator.rig_client import RigClient
from capture_agent.recorder.recorder import Recorder
from capture_agent.sources.sim_source import SimSource
from protocol.formats.camera_config import SimSourceConfig
from protocol.formats.node_config import NodeConfig
from protocol.formats.rig_config import RigConfig
from protocol.session import GapKind, SessionReader
from protocol.wire import (
    Encoding,
    FrameMessage,
)
from sim.deploy import SimRig, SimRigSpec, free_ports, write_sim_rig

FPS = 15.0
PERIOD_NS = 1e9 / FPS

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    files = write_sim_rig(
        tmp_path_factory.mktemp("rig"),
        SimRigSpec(
            seed=3,
            fps=FPS,
            drop_probability=0.03,
            content_fps=0.5,
            prerender_s=2.0,
            plaintext=True,  # the capture path under test; sealed: test_sealed_session.py
        ),
    )
    sim_rig = SimRig(files).start()
    try:
        sim_rig.wait_streaming(timeout_s=300)
        yield sim_rig
    finally:
        sim_rig.close()


def _truth_sources(files) -> dict[int, SimSource]:
    """The same sim cameras the agents run, built from their own config tables."""
    out = {}
    for _node, path in files.node_configs.items():
        for cam in NodeConfig.from_toml(path).cameras:
            assert isinstance(cam, SimSourceConfig)
            src = SimSource(cam)
            out[src.serial] = src
    return out


def _record(rig: SimRig, case: str, seconds: float) -> dict:
    rig.control("start", case=case, meta={"test": case})
    time.sleep(seconds)
    return rig.control("stop")


def test_recording_matches_the_simulators_ground_truth(rig):
    summary = _record(rig, "truth-check", 6.0)
    truth_src = _truth_sources(rig.files)
    with SessionReader(summary["file"]) as reader:
        assert reader.verify() == []
        serials = reader.info.camera_serials
        assert set(serials) == set(truth_src)
        gaps = reader.gaps()
        sets = reader.sets()
        tables = {s: reader.frame_table(s) for s in serials}
        # every conf the agents read is stored with the session
        for s in serials:
            assert "[LEFT_CAM_FHD1200]" in reader.info.camera(s).factory_conf_text
        first_left, first_right = reader.frame_bytes(serials[0], 0)
        assert first_left[:2] == b"\xff\xd8" and first_right[-2:] == b"\xff\xd9"
    assert len(sets.set_unix_ns) >= 0.9 * 6.0 * FPS
    for s in serials:
        table = tables[s]
        idx = table["frame_index"]
        truth = truth_src[s].truth(
            int(table["capture_unix_ns"][0]) - 10**9, int(table["capture_unix_ns"][-1]) + 10**9
        )
        inside = (truth.frame_index >= idx[0]) & (truth.frame_index <= idx[-1])
        sent = truth.frame_index[inside & ~truth.dropped]
        # every frame the camera produced in the recording is in the file, with its true stamp
        np.testing.assert_array_equal(idx, sent)
        stamps = dict(zip(truth.frame_index.tolist(), truth.capture_unix_ns.tolist(), strict=True))
        assert [stamps[i] for i in idx.tolist()] == table["capture_unix_ns"].tolist()
        # the drop counters equal what the sim injected, at the right frame indices
        dropped = set(truth.frame_index[inside & truth.dropped].tolist())
        recorded = set()
        for g in gaps:
            if g.camera_serial == s and g.kind == GapKind.FRAME_INDEX_GAP:
                recorded |= set(
                    range(
                        g.first_missing_frame_index, g.first_missing_frame_index + g.missing_count
                    )
                )
        assert recorded == dropped
        assert summary["cameras"][str(s)]["dropped"] == len(dropped)
        assert summary["cameras"][str(s)]["transport_lost"] == 0
    # the sets match the truth: each member is the camera's frame nearest the set's time, and a
    # camera is missing only where the sim dropped that frame (or at the take's two ends)
    for k, (t_set, members) in enumerate(zip(sets.set_unix_ns, sets.members, strict=True)):
        for col, s in enumerate(serials):
            truth = truth_src[s].truth(int(t_set) - 10**9, int(t_set) + 10**9)
            nearest = int(np.argmin(np.abs(truth.capture_unix_ns - t_set)))
            if members[col] >= 0:
                row = members[col]
                assert tables[s]["frame_index"][row] == truth.frame_index[nearest]
                assert abs(int(tables[s]["capture_unix_ns"][row]) - int(t_set)) <= PERIOD_NS / 2
            elif 0 < k < len(sets.set_unix_ns) - 1:
                assert truth.dropped[nearest], f"set {k}: camera {s} missing but not dropped"
        present = [
            int(tables[s]["capture_unix_ns"][m])
            for s, m in zip(serials, members, strict=True)
            if m >= 0
        ]
        assert sets.spread_ns[k] == max(present) - min(present)


def test_session_tools_read_the_recording(rig, tmp_path):
    from tests.conftest import run_egosurg

    summary = _record(rig, "tools", 2.0)
    out = run_egosurg("session", "info", summary["file"])
    assert out.returncode == 0, out.stderr
    assert "synchronised sets" in out.stdout and "SN" in out.stdout
    out = run_egosurg("session", "verify", summary["file"])
    assert out.returncode == 0 and "OK" in out.stdout
    out = run_egosurg(
        "session", "export-frames", summary["file"], "--out", str(tmp_path), "--sets", "0:2"
    )
    assert out.returncode == 0, out.stderr
    assert len(list(tmp_path.glob("set_000000/*.png"))) == 8  # 4 cameras x left/right
    out = run_egosurg("status", "--config", str(rig.files.rig_config))  # its keys too
    assert out.returncode == 0 and "streaming" in out.stdout


def test_two_simultaneous_starts_record_one_case(rig):
    client = RigClient.connect(config=str(rig.files.rig_config))
    results: list[object] = []

    def start(name: str) -> None:
        try:
            results.append(client.start(name))
        except CommandRefusedError as exc:
            results.append(exc)

    threads = [threading.Thread(target=start, args=(f"race-{i}",)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    ok = [r for r in results if isinstance(r, dict)]
    refused = [r for r in results if isinstance(r, CommandRefusedError)]
    assert len(ok) == 1 and len(refused) == 1
    assert "already recording" in str(refused[0])
    time.sleep(1.0)
    summary = client.stop()
    assert summary["file"] == ok[0]["file"]
    with SessionReader(summary["file"]) as reader:
        assert reader.info.closed_cleanly and not [p for p in reader.verify() if "error" in p]
    with pytest.raises(CommandRefusedError, match="not recording"):
        client.stop()


ROGUE_SERIAL = 99  # the camera of the rogue publisher below: listed, never streaming until it sends


def _in_process_recorder(rig, tmp_path, **overrides) -> tuple[Recorder, RigClient]:
    cfg = RigConfig.from_toml(rig.files.rig_config)
    port = free_ports(1)[0]
    values = {
        **cfg.__dict__,
        "control_bind": f"tcp://127.0.0.1:{port}",
        "output_dir": str(tmp_path / "sessions"),
        **overrides,
    }
    rec = Recorder(RigConfig(**values))
    rec.start()
    client = RigClient(f"tcp://127.0.0.1:{port}", config=str(rig.files.rig_config))
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        st = client.status()
        if all(c["streaming"] for c in st["cameras"] if c["serial"] != ROGUE_SERIAL) and all(
            a["alive"] for a in st["agents"] if a["node_id"] != "rogue"
        ):
            return rec, client
        time.sleep(0.3)
    raise AssertionError("cameras never streamed to the in-process recorder")


def test_start_is_refused_when_ptp_is_not_locked(rig, tmp_path):
    rec, client = _in_process_recorder(rig, tmp_path, require_ptp_lock=True)
    try:
        with pytest.raises(CommandRefusedError) as info:
            client.start("no-ptp")
        assert "PTP" in str(info.value) and "orin-" in str(info.value)
        assert not list((tmp_path / "sessions").glob("*.h5"))
    finally:
        rec.stop()


def test_start_is_refused_when_the_disk_is_too_full(rig, tmp_path):
    free_gb = shutil.disk_usage(tmp_path).free / 1e9
    rec, client = _in_process_recorder(rig, tmp_path, disk_reserve_gb=free_gb + 1000.0)
    try:
        with pytest.raises(CommandRefusedError, match="not enough disk"):
            client.start("full-disk")
        assert not list((tmp_path / "sessions").glob("*.h5"))
    finally:
        rec.stop()


@pytest.fixture
def small_disk(tmp_path):
    """A 120 MB filesystem of its own (tmpfs, as root), so other disk traffic cannot interfere;
    without root, the real disk with a reserve set 40 MB under its free space."""
    mount = tmp_path / "small"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=120m", "tmpfs", str(mount)], capture_output=True
    )
    if done.returncode == 0:
        yield mount, 0.05
        subprocess.run(["umount", "-l", str(mount)], check=False)
    else:
        yield mount, (shutil.disk_usage(mount).free - 40e6) / 1e9


def test_recording_stops_cleanly_before_the_disk_fills(rig, tmp_path, small_disk):
    directory, reserve_gb = small_disk
    rec, client = _in_process_recorder(rig, directory, disk_reserve_gb=reserve_gb)
    try:
        started = client.start("filling", planned_duration_min=0.001)
        deadline = time.monotonic() + 180  # a busy machine fills it slower
        while client.status()["recording"] and time.monotonic() < deadline:
            time.sleep(0.5)
        st = client.status()
        assert not st["recording"], "the recorder kept recording into the reserve"
        assert "reserve" in st["last_recording"]["reason"]
        assert shutil.disk_usage(directory).free > 0.8 * reserve_gb * 1e9  # stopped in time
        with SessionReader(started["file"]) as reader:
            assert reader.info.closed_cleanly
            assert reader.frame_count(reader.info.camera_serials[0]) > 10
            assert not [p for p in reader.verify() if p.startswith("error")]
    finally:
        rec.stop()


def test_malformed_messages_are_counted_and_the_receiver_keeps_going(rig, tmp_path):
    from capture_agent.operator.keys_cli import generate
    from protocol.formats.rig_config import AgentEndpoint

    ctx = zmq.Context.instance()
    rogue = ctx.socket(zmq.PUB)
    rogue.setsockopt(zmq.LINGER, 0)
    public, secret = generate(tmp_path / "keys", "rogue")  # a listed key that sends junk
    rogue.curve_publickey, rogue.curve_secretkey = zmq.auth.load_certificate(secret)
    rogue.curve_server = True
    port = rogue.bind_to_random_port("tcp://127.0.0.1")
    cfg = RigConfig.from_toml(rig.files.rig_config)
    agents = (
        *cfg.agents,
        AgentEndpoint(
            node_id="rogue",
            frames=f"tcp://127.0.0.1:{port}",
            control="tcp://127.0.0.1:1",
            public_key=str(public),
            cameras=(ROGUE_SERIAL,),  # the recorder takes frames only from the rig's listed cameras
        ),
    )
    rec, client = _in_process_recorder(rig, tmp_path, agents=agents)
    try:
        time.sleep(0.5)  # let the SUB connection settle
        good = FrameMessage(
            node_id="rogue",
            camera_serial=99,
            frame_index=0,
            seq=0,
            capture_unix_ns=time.time_ns(),
            host_receive_unix_ns=time.time_ns(),
            ptp_offset_ns=0,
            ptp_locked=True,
            encoding=Encoding.RAW_BGR8,
            width=2,
            height=2,
            left=bytes(12),
            right=bytes(12),
        )
        header = bytearray(good.header())
        header[4:6] = (7).to_bytes(2, "little")  # a wire version from the future
        for _ in range(3):
            rogue.send_multipart([b"garbage"])
            rogue.send_multipart([b"EGSF", b"too short"])
            rogue.send_multipart([bytes(header), bytes(12), bytes(12)])
        rogue.send_multipart(good.to_parts())
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            st = client.status()
            if (
                st["malformed_messages"] >= 6
                and st["unknown_version_messages"] >= 3
                and any(c["serial"] == 99 for c in st["cameras"])
            ):
                break
            time.sleep(0.2)
        assert st["malformed_messages"] == 6
        assert st["unknown_version_messages"] == 3
        assert any(c["serial"] == 99 for c in st["cameras"])  # a valid frame after the junk
        assert all(c["streaming"] for c in st["cameras"] if c["serial"] != 99)
    finally:
        rec.stop()
        rogue.close(linger=0)


def test_a_killed_agent_leaves_a_recorded_gap_and_spares_the_others(rig):
    rig.control("start", case="agent-restart")
    time.sleep(2.5)
    killed_at = time.time_ns()
    rig.signal("agent-orin-b", signal.SIGKILL)
    time.sleep(2.0)
    rig.start_agent("orin-b")
    rig.wait_streaming(timeout_s=180)
    time.sleep(2.0)
    summary = rig.control("stop")
    truth_src = _truth_sources(rig.files)
    with SessionReader(summary["file"]) as reader:
        gaps = reader.gaps()
        tables = {s: reader.frame_table(s) for s in reader.info.camera_serials}
    for node, serials in rig.files.serials_by_node.items():
        for s in serials:
            table = tables[s]
            stamps = table["capture_unix_ns"]
            kinds = {g.kind for g in gaps if g.camera_serial == s}
            if node == "orin-b":
                # the outage is on record: frames missing across the kill, and a reconnect
                before = stamps[stamps < killed_at]
                after = stamps[stamps > killed_at + 2e9]
                assert len(before) and len(after)
                # the restarted agent is a new stream: a RECONNECT record spans the outage
                outage = [
                    g
                    for g in gaps
                    if g.camera_serial == s
                    and g.kind == GapKind.RECONNECT
                    and g.missing_count >= FPS
                    and g.start_unix_ns < killed_at < g.end_unix_ns
                ]
                assert len(outage) == 1, "no gap record spans the dead agent's time"
            else:
                # the other node's cameras lost nothing beyond what the sim itself dropped
                idx = table["frame_index"]
                truth = truth_src[s].truth(int(stamps[0]) - 10**9, int(stamps[-1]) + 10**9)
                inside = (truth.frame_index >= idx[0]) & (truth.frame_index <= idx[-1])
                np.testing.assert_array_equal(idx, truth.frame_index[inside & ~truth.dropped])
                assert kinds <= {GapKind.FRAME_INDEX_GAP, GapKind.TIME_GAP}


def test_operator_console_rig_object(rig):
    """What `egosurg shell` gives the operator: a connected rig with readable results."""
    from capture_agent.operator.console import Rig

    console_rig = Rig(RigClient.connect(config=str(rig.files.rig_config)))
    text = repr(console_rig.status())
    assert "streaming" in text and "disk" in text
    serial = next(iter(rig.files.camera_index_by_serial))
    img = console_rig.last_frame(serial)
    assert img.shape == (600, 960, 3) and img.dtype == np.uint8 and img.std() > 10
    refused = console_rig.start("bad/case name")  # the reason, not a traceback
    assert not refused and "file name" in repr(refused) and "\n" not in repr(refused)
    console_rig.start("console-case", surgeon="A. Smith")
    time.sleep(1.0)
    summary = console_rig.stop()
    assert "console-case" in repr(summary) and "frames" in repr(summary)
    with SessionReader(summary["file"]) as reader:
        assert reader.info.case_metadata == {"surgeon": "A. Smith"}


def test_a_killed_recorder_leaves_a_readable_file(rig):
    started = rig.control("start", case="recorder-crash")
    time.sleep(4.0)
    killed_at = time.time_ns()
    rig.signal("recorder", signal.SIGKILL)
    with SessionReader(started["file"]) as reader:
        assert not reader.info.closed_cleanly
        assert not [p for p in reader.verify() if p.startswith("error")]
        sets = reader.sets()
        serials = reader.info.camera_serials
        tables = {s: reader.frame_table(s) for s in serials}
        for s in serials:
            left, right = reader.frame_bytes(s, reader.frame_count(s) - 1)
            assert left[-2:] == b"\xff\xd9" and right[:2] == b"\xff\xd8"
    # Every set (and so every frame) the recorder had completed more than one second before the
    # kill is in the file: its last set in the file was completed (its last member received)
    # less than a second before the kill. Counted on the recorder's clock of arrival: capture
    # times also carry the agents' delivery latency, which a loaded machine stretches.
    received = [
        int(tables[s]["recorder_receive_unix_ns"][m])
        for s, m in zip(serials, sets.members[-1], strict=True)
        if m >= 0
    ]
    assert max(received) >= killed_at - 1.0e9
    assert np.all(np.diff(sets.set_unix_ns) < 1.6 * PERIOD_NS)  # no hole in the sets before
    for table in tables.values():
        assert table["recorder_receive_unix_ns"][-1] >= killed_at - 1.0e9
    rig.start_recorder()  # the next test (if any) gets a recorder back


def test_a_sim_rig_of_more_cameras(tmp_path):
    """SimRigSpec.cameras: camera k >= 4 is camera k % 4 of the world of seed + k // 4, on that
    camera index's node, with its own serial; the agents' and the recorder's files agree."""
    files = write_sim_rig(tmp_path, SimRigSpec(seed=3, cameras=6, fps=FPS))
    cfg = RigConfig.from_toml(files.rig_config)
    serials = [s for a in cfg.agents for s in a.cameras]
    assert len(serials) == len(set(serials)) == 6
    assert {a.node_id: a.cameras for a in cfg.agents} == files.serials_by_node
    seeds = []
    for node, path in files.node_configs.items():
        tables = NodeConfig.from_toml(path).cameras
        assert all(isinstance(t, SimSourceConfig) for t in tables)
        seeds += [t.seed for t in tables]  # type: ignore[union-attr]
        assert [t.camera_index for t in tables] == [  # type: ignore[union-attr]
            files.camera_index_by_serial[s] for s in files.serials_by_node[node]
        ]
    assert sorted(seeds) == [3, 3, 3, 3, 4, 4]  # cameras 4 and 5 come from the world of seed 4
    with pytest.raises(ValueError, match="cameras"):
        SimRigSpec(cameras=0)
