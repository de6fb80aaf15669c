"""The recorder's receive queue is bounded in bytes, measured on real sockets and a real sender
process: a recorder that stops reading while an agent sends gigabytes holds what
``receive_buffer_mb`` allows, not what was sent (capture_agent/recorder/links.py, receive_hwm)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import zmq

from capture_agent.recorder.links import receive_hwm
from capture_agent.recorder.recorder import Recorder
from protocol.wire.frame_limits import frame_message_max_bytes
from tests.helpers import loopback_rig_config

IMAGE_BYTES = 8 * 1024 * 1024  # a rig.toml that allows 8 MiB images
MESSAGES = 60  # two 8 MiB images each: about 1 GB sent
SLACK_BYTES = 96e6  # the interpreter's own growth, the message being decoded, allocator rounding

SENDER = textwrap.dedent(
    """
    import sys, time, zmq
    from tests.helpers import frame_message
    port, count, size = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    pub = zmq.Context.instance().socket(zmq.PUB)
    pub.setsockopt(zmq.SNDHWM, 0)  # the agent's side keeps everything: the recorder must bound
    pub.bind(f"tcp://127.0.0.1:{port}")
    # one buffer (a JPEG by its markers), sent without copies: the sender stays small
    image = b"\\xff\\xd8" + bytes(size - 4) + b"\\xff\\xd9"
    time.sleep(1.5)  # the recorder's SUB joins
    now = time.time_ns()
    for i in range(count):
        parts = frame_message("n0", 11, i, i, now + i, image).to_parts()
        pub.send_multipart(parts, copy=False)
    print("sent", flush=True)
    time.sleep(60)
    """
)


def _rss_bytes() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS in /proc/self/status")


def test_a_recorder_that_stops_reading_holds_only_its_receive_buffer(tmp_path):
    """About 1 GB of 2 x 8 MiB frames sent to a recorder that reads nothing: its memory grows by
    at most ``receive_buffer_mb`` (8 messages here), and its queue is really full."""
    cfg = loopback_rig_config(tmp_path / "sessions", cameras=(11,))
    largest = frame_message_max_bytes(IMAGE_BYTES)
    cfg = dataclasses.replace(
        cfg, max_image_bytes=IMAGE_BYTES, receive_buffer_mb=8 * largest / 1e6 + 1
    )
    hwm = receive_hwm(cfg, cfg.agents[0])
    assert hwm == 8
    port = int(cfg.agents[0].frames.rsplit(":", 1)[1])
    recorder = Recorder(cfg)
    sender = subprocess.Popen(
        [sys.executable, "-c", SENDER, str(port), str(MESSAGES), str(IMAGE_BYTES)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    try:
        recorder.links.open()
        before = _rss_bytes()
        assert sender.stdout is not None and sender.stdout.readline().strip() == "sent"
        peak, stable_since = before, time.monotonic()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and time.monotonic() - stable_since < 3:
            time.sleep(0.25)
            rss = _rss_bytes()
            if rss > peak + 1e6:
                peak, stable_since = rss, time.monotonic()
        grown = peak - before
        assert grown <= cfg.receive_buffer_mb * 1e6 + SLACK_BYTES, (
            f"the recorder took {grown / 1e6:.0f} MB for its receive queue, more than "
            f"receive_buffer_mb = {cfg.receive_buffer_mb:.0f} MB "
            f"(sent {MESSAGES * largest / 1e9:.1f} GB)"
        )
        (sub,) = recorder.links.subs
        queued = 0
        while True:
            try:
                sub.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            queued += 1
        assert queued >= hwm, f"the queue held {queued} messages: it never filled"
    finally:
        sender.kill()
        sender.wait()
        recorder.links.close()
