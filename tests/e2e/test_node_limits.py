"""A node with a valid key cannot corrupt the record: real recorder and agent processes (sim/
deploy.py's SimRig, CURVE on), with orin-b replaced by a compromised Jetson written here, which
holds orin-b's real keys and endpoints. The session folder is a tmpfs of known size.

What an operator relies on: one node's burst far above its frame rate does not stop the take
(the disk check plans with the configured rates) and does not cost the other node a frame; the
excess is refused and counted (status, stop summary, session events); a frame index that jumps by
1e12 is a reconnect with sane totals; a stamp that goes back is refused and counted, so the file
verifies clean; ``session info`` and ``session verify`` list what happened. The recorder's peak
memory under the burst is measured (psutil RSS)."""

from __future__ import annotations

import os
import subprocess
import threading
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest
import zmq
import zmq.auth

from capture_agent.operator.control import format_status, format_summary
from protocol.camera import Resolution
from protocol.session import EventKind, GapKind, SessionReader
from protocol.wire import ControlReply, ControlRequest
from sim.deploy import SimRig, SimRigSpec, write_sim_rig
from tests.helpers import frame_message, run_egosurg

FPS = 15.0
BURST_FPS = 10 * FPS  # the compromised node's burst on one camera
BURST_S = 4.0
NORMAL_IMAGE = 20_000
BURST_IMAGE = 300_000
HEADROOM_BYTES = 250e6  # free space above the reserve at the start
JUMP = 10**12
RSS_LIMIT_MB = 600  # the recorder's bound under the burst (its queues' bounds, generously)

pytestmark = pytest.mark.slow


def _jpeg(n: int) -> bytes:
    return b"\xff\xd8" + os.urandom(n - 4) + b"\xff\xd9"


class RogueNode:
    """orin-b as a compromised or buggy Jetson: its own keys and endpoints. It streams both its
    cameras at the rig's fps with true stamps and answers ``status``; ``burst`` sends one
    camera at 10x its rate, ``step_back`` stamps one frame 1 ms before the camera's last,
    ``jump`` makes a camera's frame index jump by 1e12."""

    def __init__(self, node_toml: Path, serials: tuple[int, ...]) -> None:
        cfg = tomllib.loads(node_toml.read_text())
        public, secret = zmq.auth.load_certificate(node_toml.parent / cfg["security"]["secret_key"])
        self.ctx = zmq.Context()
        self.pub = self._server(zmq.PUB, public, secret, cfg["frames_bind"])
        self.pub.setsockopt(zmq.SNDHWM, 0)  # nothing lost here: what is sent reaches the link
        self.rep = self._server(zmq.REP, public, secret, cfg["control_bind"])
        self.serials = serials
        self.index = dict.fromkeys(serials, 0)
        self.last_stamp = dict.fromkeys(serials, 0)
        self.seq = 0
        self.sent = dict.fromkeys(serials, 0)
        self.burst_until = 0.0
        self.burst_sent = 0
        self.step_back_once = False
        self.jump_once = False
        self.normal = _jpeg(NORMAL_IMAGE)
        self.big = _jpeg(BURST_IMAGE)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rogue-orin-b", daemon=True)
        self._thread.start()

    def _server(self, kind: int, public: bytes, secret: bytes, bind: str) -> zmq.Socket:
        s = self.ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        s.curve_server = True
        s.curve_publickey, s.curve_secretkey = public, secret
        s.bind(bind)
        return s

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.pub.close(linger=0)
        self.rep.close(linger=0)
        self.ctx.term()

    def _send(self, serial: int, image: bytes, stamp: int) -> None:
        msg = frame_message(
            "orin-b", serial, self.index[serial], self.seq, stamp, image, size_px=(960, 600)
        )
        self.pub.send_multipart(msg.to_parts(), copy=False)
        self.index[serial] += 1
        self.seq += 1
        self.sent[serial] += 1
        self.last_stamp[serial] = stamp

    def _run(self) -> None:  # the one thread that touches the sockets
        a, b = self.serials
        next_frame = next_burst = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_frame:
                next_frame += 1 / FPS
                stamp = time.time_ns()
                self._send(a, self.normal, stamp)
                if self.jump_once:
                    self.index[b] += JUMP
                    self.jump_once = False
                if self.step_back_once:
                    self._send(b, self.normal, self.last_stamp[b] - 1_000_000)
                    self.step_back_once = False
                self._send(b, self.normal, stamp + 1000)
            if now < self.burst_until and now >= next_burst:
                next_burst += 1 / BURST_FPS
                self._send(a, self.big, time.time_ns())
                self.burst_sent += 1
            elif now >= self.burst_until:
                next_burst = now
            if self.rep.poll(0):
                self._answer()
            time.sleep(0.001)

    def _answer(self) -> None:
        req = ControlRequest.from_bytes(self.rep.recv())
        width, height = Resolution.SVGA.size
        info = [
            {"camera_serial": s, "resolution": "SVGA", "width": width, "height": height,
             "fps": FPS, "encoding": "jpeg", "factory_conf": None}
            for s in self.serials
        ]  # fmt: skip
        reply = ControlReply(ok=True, result={"cameras_info": info}, request_id=req.request_id)
        self.rep.send(reply.to_bytes())


@pytest.fixture
def tmpfs(tmp_path) -> Iterator[Path]:
    mount = tmp_path / "sessions"
    mount.mkdir()
    cmd = ["mount", "-t", "tmpfs", "-o", "size=1000m,mode=0700", "tmpfs", str(mount)]
    done = subprocess.run(cmd, capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs (needs root): {done.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.fixture
def rig(tmp_path, tmpfs) -> Iterator[tuple[SimRig, RogueNode]]:
    files = write_sim_rig(
        tmp_path / "rig",
        SimRigSpec(
            seed=7,
            fps=FPS,
            drop_probability=0.0,
            content_fps=0.5,
            prerender_s=2.0,
            plaintext=True,  # the capture path under test; sealed: test_sealed_session.py
        ),
    )
    # the sessions on the tmpfs, with HEADROOM_BYTES above the reserve
    reserve_gb = (psutil.disk_usage(str(tmpfs)).free - HEADROOM_BYTES) / 1e9
    text = files.rig_config.read_text()
    text = text.replace(f'output_dir = "{files.session_dir}"', f'output_dir = "{tmpfs}"')
    text = text.replace("disk_reserve_gb = 0.5", f"disk_reserve_gb = {reserve_gb:.6f}")
    text = text.replace("planned_duration_min = 1.0", "planned_duration_min = 0.2")
    files.rig_config.write_text(text)
    rogue = RogueNode(files.node_configs["orin-b"], files.serials_by_node["orin-b"])
    sim = SimRig(files)
    try:
        sim.start_agent("orin-a")
        sim.start_recorder()
        sim.wait_streaming(timeout_s=300)
        yield sim, rogue
    finally:
        sim.close()
        rogue.close()


def _operator_reads_the_refusals(status: dict, summary: dict, camera_refused: str) -> None:
    """The refusals in the words of `egosurg status` and of the stop summary."""
    assert "over their camera's rate" in format_status(status)
    printed = format_summary(summary)
    assert camera_refused in printed
    assert "session events: " in printed and "rate_capped" in printed


def test_a_compromised_node_cannot_stop_the_take_or_corrupt_the_record(rig, tmp_path):
    sim, rogue = rig
    honest = sim.files.serials_by_node["orin-a"]
    burst_cam, other_cam = rogue.serials
    recorder = psutil.Process(sim.procs["recorder"].pid)
    sim.control("start", case="burst")
    time.sleep(2.0)
    rss_mb = [recorder.memory_info().rss / 2**20]
    rogue.burst_until = time.monotonic() + BURST_S
    while time.monotonic() < rogue.burst_until + 2.0:
        rss_mb.append(recorder.memory_info().rss / 2**20)
        status = sim.control("status")
        assert status["recording"], f"the take stopped: {status.get('last_recording')}"
        time.sleep(0.2)
    rogue.step_back_once = True
    time.sleep(1.0)
    rogue.jump_once = True
    time.sleep(2.0)
    summary = sim.control("stop")
    status = sim.control("status")  # after the stop: every message of the burst handled
    print(f"recorder RSS: start {rss_mb[0]:.0f} MB, peak {max(rss_mb):.0f} MB under the burst")
    print(f"burst: {rogue.burst_sent} frames sent at {BURST_FPS:g}/s for {BURST_S:g} s")
    assert summary["reason"] == "stopped by request"
    assert max(rss_mb) < RSS_LIMIT_MB

    # the honest node lost nothing: every frame it sent is in the file
    for s in honest:
        cam = summary["cameras"][str(s)]
        assert cam["not_written_disk_stalled"] == 0 and cam["refused"] == 0, cam
        assert (cam["dropped"], cam["transport_lost"], cam["reconnects"]) == (0, 0, 0), cam
        assert cam["frames"] >= 0.9 * FPS * summary["duration_s"], cam

    # the excess was refused and counted, in the summary, the session events and status
    burst = summary["cameras"][str(burst_cam)]
    capped = burst["refused"]
    allowed = 1.5 * FPS * (BURST_S + 1.0)  # the cap's rate and its second of burst
    assert capped >= rogue.burst_sent + FPS * BURST_S - allowed - 2, (
        f"refused over the rate cap: {capped} of {rogue.sent[burst_cam]} frames of the camera"
    )
    cams = {c["serial"]: c for c in status["cameras"]}
    assert cams[burst_cam]["frames_refused_rate"] >= capped  # and any during the stop
    assert (burst["dropped"], burst["transport_lost"]) == (0, 0), burst
    assert cams[other_cam]["frames_refused_stamp"] == 1
    _operator_reads_the_refusals(status, summary, f"SN{burst_cam} {capped}")

    with SessionReader(summary["file"]) as r:
        assert r.verify() == []  # the stamp that went back is not in the file
        events = r.events()
        gaps = [g for g in r.gaps() if g.camera_serial == other_cam]
        stored = r.summary()

    def occurrences(kind: EventKind, serial: int) -> int:
        return sum(e.count for e in events if e.kind == kind and e.camera_serial == serial)

    assert occurrences(EventKind.RATE_CAPPED, burst_cam) == capped
    assert occurrences(EventKind.STAMP_BACKWARDS, other_cam) == 1
    assert occurrences(EventKind.IMPLAUSIBLE_JUMP, other_cam) == 1
    assert len(events) < 100  # a flood of refusals is a few counted rows
    # the refused frame is missing from the file (counted as refused); the jump is a
    # reconnect, not 1e12 dropped frames
    assert [(g.kind, g.missing_count) for g in gaps if g.kind != GapKind.TIME_GAP] == [
        (GapKind.FRAME_INDEX_GAP, 1),
        (GapKind.RECONNECT, 0),
    ]
    other = summary["cameras"][str(other_cam)]
    assert (other["dropped"], other["transport_lost"]) == (0, 0), other
    assert (other["refused"], other["reconnects"]) == (1, 1), other
    # the file's totals: what is missing from it is what was refused, nothing made up
    missing = {s: stored[str(s)]["missing_frames"] for s in (*honest, *rogue.serials)}
    assert missing == {**dict.fromkeys(honest, 0), burst_cam: capped, other_cam: 1}

    info = run_egosurg("session", "info", summary["file"], timeout=120)
    assert info.returncode == 0, info.stderr
    assert f"event rate_capped: {capped} (orin-b {capped})" in info.stdout
    assert "event stamp_backwards: 1 (orin-b 1)" in info.stdout
    verify = run_egosurg("session", "verify", summary["file"], timeout=120)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    assert f"event rate_capped: {capped} time(s)" in verify.stdout
    assert "event implausible_jump: 1 time(s)" in verify.stdout
