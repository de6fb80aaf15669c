"""The image size limit is the documented one: rig.toml's ``max_image_bytes``, exactly.

Real ZeroMQ sockets on loopback: the largest legal image crosses a CURVE link configured as the
recorder configures its SUB sockets (the socket limit allows for CURVE's framing), and an image
over the limit is refused where frames are decoded, counted in ``status``, without costing the
link."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zmq

from capture_agent.recorder.recorder import Recorder
from capture_agent.security import LinkSecurity, harden, make_client
from protocol.formats.rig_config import RigConfig
from protocol.wire import ControlReply, ControlRequest, FrameMessage, decode_published
from protocol.wire.frame import ImageTooLargeError
from protocol.wire.frame_limits import (
    CURVE_MESSAGE_OVERHEAD_BYTES,
    LARGEST_IMAGE_BYTES,
    frame_part_max_bytes,
)
from tests.capture_agent.spec_agent import SpecAgent
from tests.helpers import frame_message, loopback_rig_config

LIMIT = 4096  # a small rig limit, so the test sends kilobytes


def _curve_pair(
    ctx: zmq.Context, max_image_bytes: int, slack_bytes: int = 0
) -> tuple[zmq.Socket, zmq.Socket]:
    """A CURVE PUB (an agent's) and a SUB configured as the recorder's (its limit changed by
    ``slack_bytes``), connected."""
    server_public, server_secret = zmq.curve_keypair()
    client_public, client_secret = zmq.curve_keypair()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.curve_secretkey, pub.curve_publickey = server_secret, server_public
    pub.curve_server = True
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    sub = ctx.socket(zmq.SUB)
    harden(sub, frame_part_max_bytes(max_image_bytes) + slack_bytes)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    links = LinkSecurity(public_key=client_public, secret_key=client_secret)
    make_client(sub, links, server_public)
    sub.connect(f"tcp://127.0.0.1:{port}")
    return pub, sub


def _received(pub: zmq.Socket, sub: zmq.Socket, parts: list, timeout_s: float = 10.0) -> list:
    """Publish ``parts`` until the SUB has them (a new SUB misses what comes before its
    handshake); [] when nothing arrives within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pub.send_multipart(parts, copy=False)
        if sub.poll(200):
            return sub.recv_multipart(copy=False)
    return []


def test_the_curve_overhead_is_exact():
    """CURVE_MESSAGE_OVERHEAD_BYTES is what libzmq needs: one byte less refuses the part."""
    limit = 2_000_000  # over the JSON limit, so the image sets the socket's limit
    part = b"\xff\xd8" + bytes(limit - 2)
    ctx = zmq.Context()
    try:
        for slack, arrives in ((0, True), (-1, False)):
            pub, sub = _curve_pair(ctx, limit, slack)
            got = _received(pub, sub, [part], timeout_s=10.0 if arrives else 2.0)
            pub.close(linger=0)
            sub.close(linger=0)
            assert bool(got) is arrives, f"limit {frame_part_max_bytes(limit) + slack}"
    finally:
        ctx.term()


def test_the_largest_legal_image_crosses_a_curve_link():
    """raw_bgr8 at HD1200, exactly the default max_image_bytes, over CURVE."""
    image = np.zeros((1200, 1920, 3), np.uint8)
    assert image.nbytes == LARGEST_IMAGE_BYTES
    msg = frame_message(
        "n0", 11, 0, 0, time.time_ns(), image.tobytes(), encoding="raw_bgr8", size_px=(1920, 1200)
    )
    ctx = zmq.Context()
    try:
        pub, sub = _curve_pair(ctx, LARGEST_IMAGE_BYTES)
        got = _received(pub, sub, msg.to_parts())
        pub.close(linger=0)
        sub.close(linger=0)
    finally:
        ctx.term()
    assert got, "the largest legal image did not cross the CURVE link"
    decoded = decode_published(got, max_image_bytes=LARGEST_IMAGE_BYTES)
    assert isinstance(decoded, FrameMessage) and decoded.left_bytes == LARGEST_IMAGE_BYTES


def test_an_image_over_the_limit_is_refused_where_decoded_naming_the_numbers():
    msg = frame_message("n0", 11, 0, 0, 1, b"\xff\xd8" + bytes(LIMIT - 1))
    with pytest.raises(ImageTooLargeError) as err:
        decode_published(msg.to_parts(), max_image_bytes=LIMIT)
    assert f"{LIMIT + 1} bytes" in str(err.value) and f"max_image_bytes = {LIMIT}" in str(err.value)
    decode_published(msg.to_parts(), max_image_bytes=LIMIT + 1)  # at the limit: legal


@pytest.fixture
def recorder(tmp_path) -> Iterator[RigConfig]:
    """A recorder (in this process) whose rig allows images of LIMIT bytes; its config."""
    config = dataclasses.replace(loopback_rig_config(tmp_path), max_image_bytes=LIMIT)
    rec = Recorder(config)
    rec.start()
    try:
        yield config
    finally:
        rec.stop()


def _control(config: RigConfig, request: ControlRequest) -> ControlReply:
    """One request to the recorder's control socket (a plaintext rig)."""
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, 10000)
    try:
        sock.connect(config.control_bind)
        sock.send(request.to_bytes())
        return ControlReply.from_bytes(sock.recv())
    finally:
        sock.close(linger=0)


def _status(config: RigConfig) -> dict:
    return _control(config, ControlRequest(verb="status")).result


def test_an_image_just_over_the_limit_is_counted_and_the_link_stays(recorder):
    """An image over max_image_bytes by less than CURVE's framing passes the socket's limit: the
    recorder refuses it where it decodes frames, counts it, and keeps hearing the agent."""
    config = recorder
    over = LIMIT + CURVE_MESSAGE_OVERHEAD_BYTES // 2
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.bind(config.agents[0].frames)
    try:
        deadline = time.monotonic() + 10.0
        status: dict = {}
        index = 0
        while time.monotonic() < deadline:
            now = time.time_ns()
            big = frame_message("n0", 11, index, index, now, b"\xff\xd8" + bytes(over - 2))
            small = frame_message("n0", 11, index + 1, index + 1, now, b"\xff\xd8" + bytes(98))
            pub.send_multipart(big.to_parts())
            pub.send_multipart(small.to_parts())
            index += 2
            time.sleep(0.05)
            status = _status(config)
            camera = next(c for c in status["cameras"] if c["serial"] == 11)
            if status["images_over_limit"] and camera["streaming"]:
                break
        assert status["images_over_limit"] >= 1, status
        assert camera["streaming"], status
        link = status["agents"][0]["link"]
        assert link["state"] == "up" and link["drops"] == 0, link
    finally:
        pub.close(linger=0)
        ctx.term()


def test_a_start_with_a_camera_whose_raw_images_exceed_the_limit_is_refused_naming_them(tmp_path):
    """An agent whose camera reports raw_bgr8 at HD1200 on a rig sized for 2 MB images: the
    start is refused with the camera, the numbers and what to set."""
    config = dataclasses.replace(
        loopback_rig_config(tmp_path, cameras=(7001,), fps=15.0), max_image_bytes=2_000_000
    )
    agent_link = config.agents[0]

    def raw_hd1200(result: dict) -> dict:
        for info in result["cameras_info"]:
            info.update(resolution="HD1200", width=1920, height=1200, encoding="raw_bgr8")
        return result

    agent = SpecAgent(
        node_id="n0",
        serials=(7001,),
        frames_bind=agent_link.frames,
        control_bind=agent_link.control,
        status_result=raw_hd1200,
    ).start()
    rec = Recorder(config)
    rec.start()
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            if any(c["streaming"] for c in _status(config)["cameras"]):
                break
            time.sleep(0.1)
        reply = _control(config, ControlRequest(verb="start", args={"case": "big"}))
    finally:
        rec.stop()
        agent.stop()
    assert not reply.ok
    assert "camera 7001 on n0 sends raw_bgr8 images of 1920x1200x3 = 6912000 bytes" in reply.error
    assert "max_image_bytes = 2000000" in reply.error
    assert "set max_image_bytes = 6912000" in reply.error
