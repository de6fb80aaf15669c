"""The capture agent in-process, on real loopback sockets: a hung or vanished camera is reported
and reopened while the node's other camera keeps streaming."""

from __future__ import annotations

import itertools
import time

import pytest
import zmq

from capture_agent.agent.agent import Agent
from protocol.errors import ConfigError
from protocol.formats.node_config import NodeConfig
from protocol.wire import (
    AgentStatus,
    ControlReply,
    ControlRequest,
    FrameMessage,
    decode_published,
)
from protocol.wire.agent_info import AgentStatusReply
from tests.helpers import loopback_sim_node

FPS = 10.0


def _node(faults_cam1: list[dict]) -> NodeConfig:
    return loopback_sim_node(
        "orin-t",
        fps=FPS,
        seed=2,
        cameras=({"faults": []}, {"faults": faults_cam1}),
        watchdog_timeout_s=0.8,
        reopen_interval_s=0.3,
        status_interval_s=0.25,
    )


def _collect(cfg: NodeConfig, seconds: float) -> tuple[list[FrameMessage], list[AgentStatus]]:
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(cfg.frames_bind)
    frames, statuses = [], []
    deadline = time.monotonic() + 120.0  # until both cameras stream (opening renders content)
    try:
        while time.monotonic() < deadline:
            if (
                len({f.camera_serial for f in frames}) == 2
                and deadline > time.monotonic() + seconds
            ):
                deadline = time.monotonic() + seconds
            if sub.poll(100):
                msg = decode_published(sub.recv_multipart(copy=False))
                if isinstance(msg, FrameMessage):
                    frames.append(msg)
                else:
                    statuses.append(msg)
    finally:
        sub.close(linger=0)
    return frames, statuses


@pytest.mark.parametrize("kind", ["hang", "vanish"])
def test_a_failing_camera_is_reopened_and_its_neighbour_keeps_streaming(kind):
    cfg = _node([{"kind": kind, "at_s": 2.0, "duration_s": 2.0}])
    agent = Agent(cfg)
    agent.start()
    try:
        frames, statuses = _collect(cfg, 9.0)
    finally:
        agent.stop()
    serials = [w.serial for w in agent.workers]
    healthy, failing = serials
    by_cam = {s: [f for f in frames if f.camera_serial == s] for s in serials}
    # the healthy camera never paused: no gap longer than two frame periods
    stamps = [f.capture_unix_ns for f in by_cam[healthy]]
    assert len(stamps) > 6 * FPS
    assert max(b - a for a, b in itertools.pairwise(stamps)) < 2.5e9 / FPS
    # the failing camera stopped, was reported, was reopened, and streams again
    fstamps = [f.capture_unix_ns for f in by_cam[failing]]
    gaps = [b - a for a, b in itertools.pairwise(fstamps)]
    assert max(gaps) > 1.5e9
    assert fstamps[-1] > fstamps[0] + 6e9  # frames after the fault
    states = [c for st in statuses for c in st.cameras if c.camera_serial == failing]
    assert any(c.state in ("reopening", "stalled") for c in states)
    assert states[-1].state == "streaming" and states[-1].reopen_count >= 1
    healthy_states = [c for st in statuses for c in st.cameras if c.camera_serial == healthy]
    first = next(i for i, c in enumerate(healthy_states) if c.state == "streaming")
    assert all(c.state == "streaming" for c in healthy_states[first:])
    # seq numbers are per publisher and never skip
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


def test_agent_answers_status_and_refuses_recording_verbs():
    cfg = _node([])
    agent = Agent(cfg)
    agent.start()
    ctx = zmq.Context.instance()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.setsockopt(zmq.RCVTIMEO, 5000)
    try:
        req.connect(cfg.control_bind)
        req.send(ControlRequest(verb="status").to_bytes())
        reply = ControlReply.from_bytes(req.recv())
        assert reply.ok
        info = {c["camera_serial"]: c for c in reply.result["cameras_info"]}
        assert len(info) == 2
        assert all("[STEREO]" in c["factory_conf"] for c in info.values())
        # our own agent keeps the documented contract (docs/capture.md, "The status reply")
        checked = AgentStatusReply.from_json(reply.result, node_id=cfg.node_id)
        assert {c.camera_serial for c in checked.cameras_info} == set(info)
        req.send(ControlRequest(verb="start", args={"case": "x"}).to_bytes())
        reply = ControlReply.from_bytes(req.recv())
        assert not reply.ok and "recorder" in reply.error
    finally:
        req.close(linger=0)
        agent.stop()


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"node_id": "bad id!"}, ["node_id"]),
        ({"frames_bind": "localhost:5"}, ["frames_bind", "tcp://"]),
        ({"encoding": "png"}, ["encoding", "jpeg"]),
        ({"jpeg_quality": 0}, ["jpeg_quality"]),
        ({"cameras": []}, ["[[cameras]]"]),
        ({"framez_bind": "tcp://*:1"}, ["unknown option", "framez_bind"]),
    ],
)
def test_bad_node_config_names_the_field(change, words):
    table = {
        "node_id": "orin-a",
        "frames_bind": "tcp://*:5550",
        "control_bind": "tcp://*:5551",
        "cameras": [{"source": "sim"}],
    }
    table.update(change)
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_table(table, "node.toml")
    for w in words:
        assert w in str(info.value)
