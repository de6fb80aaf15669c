"""Links that come back: real agent and recorder processes (sim/deploy.py's SimRig, CURVE on) and a
stand-in publisher written from the documented contract (tests/capture_agent/spec_agent.py) that
holds a node's real key. What an operator relies on: the largest legal image travels over the
default CURVE links; a link cut by an oversize part, by a refused key or by a publisher swapped
mid-take comes back within seconds by itself, without restarting the recorder; each drop,
refusal and return is counted in ``status``, shown by ``egosurg status`` and, during a take,
recorded as a session event.

Measured (printed with ``-s``): the time from a drop to the link being back, and the frames of
the stand-in's camera lost across that reconnect."""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import zmq.auth

from capture_agent.operator.control import format_status
from protocol.session import EventKind, SessionReader
from protocol.wire.frame_limits import LARGEST_IMAGE_BYTES
from sim.deploy import SimRig, SimRigSpec, write_sim_rig
from tests.capture_agent.spec_agent import SpecAgent

pytestmark = pytest.mark.slow

FPS = 10.0
NODE = "orin-b"


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Iterator[SimRig]:
    files = write_sim_rig(
        tmp_path_factory.mktemp("links"),
        SimRigSpec(
            seed=5,
            fps=FPS,
            drop_probability=0.0,
            content_fps=0.5,
            prerender_s=1.0,
            plaintext=True,  # the capture path under test; sealed: test_sealed_session.py
        ),
    )
    sim_rig = SimRig(files).start()
    try:
        sim_rig.wait_streaming(timeout_s=300)
        yield sim_rig
    finally:
        sim_rig.close()


def _wait(what: str, check: Callable[[], Any], timeout_s: float) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = check()
        if got:
            return got
        time.sleep(0.1)
    raise AssertionError(f"not within {timeout_s:g} s: {what}")


def _link(rig: SimRig, node: str = NODE) -> dict[str, Any]:
    status = rig.control("status", timeout_s=5.0)
    link = next(a.get("link") for a in status["agents"] if a["node_id"] == node)
    return link or {"state": "?", "handshakes": 0, "drops": 0, "handshake_failures": 0}


def _streaming(rig: SimRig, node: str = NODE) -> bool:
    status = rig.control("status", timeout_s=5.0)
    serials = set(rig.files.serials_by_node[node])
    return serials <= {c["serial"] for c in status["cameras"] if c["streaming"]}


def _node_endpoints(rig: SimRig, node: str) -> tuple[str, str]:
    text = rig.files.node_configs[node].read_text()
    frames = re.search(r'(?m)^frames_bind = "(.+)"$', text)
    control = re.search(r'(?m)^control_bind = "(.+)"$', text)
    assert frames and control
    return frames.group(1), control.group(1)


def _stand_in(rig: SimRig, node: str) -> SpecAgent:
    """A publisher with ``node``'s own key on its endpoints, admitting the recorder's key."""
    keys = rig.files.keys_dir
    keypair = zmq.auth.load_certificate(keys / f"{node}.key_secret")
    recorder_key = zmq.auth.load_certificate(keys / "recorder.key")[0]
    frames, control = _node_endpoints(rig, node)
    return SpecAgent(
        node_id=node,
        serials=rig.files.serials_by_node[node],
        frames_bind=frames,
        control_bind=control,
        fps=FPS,
        keypair=keypair,  # type: ignore[arg-type]
        allowed_client_keys=(recorder_key,),
    )


def _restart_agent(rig: SimRig, node: str) -> float:
    """Stop the node's agent (if running), start it again; returns when it was started."""
    rig.signal(f"agent-{node}")
    rig.start_agent(node)
    return time.monotonic()


def test_raw_hd1200_over_curve_is_recorded(tmp_path):
    """The largest legal image (raw_bgr8 at HD1200, exactly max_image_bytes) over the default
    CURVE links: frames stream and are stored."""
    spec = SimRigSpec(
        plaintext=True,  # the capture path under test; sealed: test_sealed_session.py
        seed=7,
        cameras=1,
        fps=2.0,
        resolution="HD1200",
        encoding="raw_bgr8",
        drop_probability=0.0,
        content_fps=0.5,
        prerender_s=1.0,
    )
    files = write_sim_rig(tmp_path, spec)
    assert f"max_image_bytes = {LARGEST_IMAGE_BYTES}" in files.rig_config.read_text()
    with SimRig(files) as sim_rig:
        sim_rig.wait_streaming(timeout_s=120)
        started = sim_rig.control("start", case="hd1200", planned_duration_min=0.1)
        time.sleep(3.0)
        summary = sim_rig.control("stop")
    with SessionReader(started["file"]) as r:
        (serial,) = r.info.camera_serials
        table = r.frame_table(serial)
        assert len(table["frame_index"]) >= 3, summary
        left, right = r.frame_bytes(serial, 0)
        assert len(left) == len(right) == LARGEST_IMAGE_BYTES


def test_an_agent_that_refused_the_recorders_key_is_heard_once_fixed(rig, capsys):
    """The agent's allowed_keys miss the recorder's key: the link is refused, counted and shown;
    once the node's config is fixed and the agent restarted, its frames flow again without
    restarting the recorder."""
    config = rig.files.node_configs[NODE]
    good = config.read_text()
    bad = good.replace('"keys/recorder.key", ', "")
    assert bad != good, "the deployed node.toml lists the recorder's key first"
    before = _link(rig)["handshake_failures"]
    try:
        config.write_text(bad)
        _restart_agent(rig, NODE)
        link = _wait(
            "the refused handshake counted",
            lambda: (lk := _link(rig))["handshake_failures"] > before and lk,
            30.0,
        )
        assert "refused this process's key" in link["last_cause"], link
        assert link["state"] != "up"
        text = format_status(rig.control("status"))
        assert f"agent {NODE} frame link" in text and "refused handshakes" in text, text
    finally:
        config.write_text(good)
    t0 = _restart_agent(rig, NODE)
    _wait("the fixed agent's cameras streaming again", lambda: _streaming(rig), 30.0)
    back_s = time.monotonic() - t0
    link = _link(rig)
    assert link["state"] == "up" and link["reconnects"] >= 1, link
    with capsys.disabled():
        print(f"\n[links] fixed agent restarted -> its cameras streaming: {back_s:.1f} s")


def test_a_swapped_publisher_and_an_oversize_part_are_recorded_and_the_link_comes_back(rig, capsys):
    """Mid-take, the node's agent is replaced by another process holding its key (the swap is a
    session event), which then sends one part over the size limit: the link drops, is made
    again within seconds, and the drop is counted and recorded; the real agent comes back."""
    _wait("the rig streaming", lambda: _streaming(rig) and _streaming(rig, "orin-a"), 60.0)
    started = rig.control("start", case="swap", planned_duration_min=0.2)
    stand_in = _stand_in(rig, NODE)
    before = _link(rig)["handshakes"]
    try:
        rig.signal(f"agent-{NODE}")
        stand_in.start()
        link = _wait(
            "the stand-in's handshake",
            lambda: (lk := _link(rig))["state"] == "up" and lk["handshakes"] > before and lk,
            20.0,
        )
        handshakes = link["handshakes"]
        time.sleep(1.0)
        drops = _link(rig)["drops"]
        t0 = time.monotonic()
        stand_in.publish_raw([b"x" * (LARGEST_IMAGE_BYTES + 4096)])
        _wait("the drop counted", lambda: _link(rig)["drops"] > drops, 10.0)
        link = _wait(
            "the link back after the oversize part",
            lambda: (lk := _link(rig))["state"] == "up" and lk["handshakes"] > handshakes and lk,
            10.0,
        )
        reconnect_s = time.monotonic() - t0
        assert "MAXMSGSIZE" in link["last_cause"], link
        time.sleep(1.0)
    finally:
        stand_in.stop()
    sent = stand_in.frames_sent()
    rig.start_agent(NODE)
    _wait("the real agent streaming again", lambda: _streaming(rig), 60.0)
    rig.control("stop")
    with SessionReader(started["file"]) as r:
        events = [e for e in r.events() if e.node_id == NODE]
        kinds = [e.kind for e in events]
        stored = {s: r.frame_table(s) for s in rig.files.serials_by_node[NODE]}
    assert kinds.count(EventKind.LINK_DROPPED) >= 2, events  # the agent stopped; the oversize part
    assert kinds.count(EventKind.LINK_RECONNECTED) >= 2, events  # the stand-in; after the part
    assert any("MAXMSGSIZE" in e.detail for e in events), events
    serial = rig.files.serials_by_node[NODE][0]
    lost = _lost_across(sent[serial], stored[serial], t0)
    with capsys.disabled():
        print(
            f"\n[links] oversize part -> link back: {reconnect_s:.2f} s (down "
            f"{link['down_s']:.2f} s by the recorder's clock); frames of camera "
            f"{serial} lost across that reconnect: {lost} at {FPS:g} fps"
        )
    assert lost <= FPS * 10


def _lost_across(sent: list[tuple[int, int]], table: dict[str, np.ndarray], t0: float) -> int:
    """Frames the stand-in sent from a second before the oversize part on that are not stored."""
    since_ns = time.time_ns() - int((time.monotonic() - t0 + 1.0) * 1e9)
    stamps = set(table["capture_unix_ns"].tolist())
    return sum(1 for _, ns in sent if ns >= since_ns and ns not in stamps)
