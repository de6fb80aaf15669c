"""The recorder and the agent cannot be stopped or exhausted by input.

A real recorder (its I/O thread running) and a real agent (two simulated cameras) on loopback,
plaintext links (CURVE is test_security.py's), recording one take while every attack of
the issue is tried on them: garbage on both control sockets, hostile start arguments, a rogue
publisher making up cameras, forging another node's camera and stamping frames hours away.
After each attack the recorder still records (frames keep reaching the file) and answers, and
the attack is refused and counted in ``status``. The last test stops the take and checks the
file. A "puppet" agent driven by the test (node ``puppet``, camera 77) and an ``open`` link
that rig.toml lists without cameras carry what the tests inject.
"""

from __future__ import annotations

import gc
import json
import math
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from pathlib import Path

import numpy as np
import pytest
import zmq

from capture_agent.agent.agent import Agent
from capture_agent.daemon import Progress, run_until_signal
from capture_agent.operator.control import format_status, format_summary
from capture_agent.recorder.intake import MAX_UNLISTED_CAMERAS
from capture_agent.recorder.recorder import Recorder
from capture_agent.recorder.start import StartRefused, start_args
from capture_agent.recorder.sync import SyncConfig, Synchroniser, group_offline
from protocol.formats.node_config import NodeConfig
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.formats.sealing_config import RigSealingConfig
from protocol.formats.security_config import RigSecurityConfig
from protocol.session import SessionReader
from protocol.toml_config import dumps
from protocol.wire import MAX_JSON_BYTES, ControlReply, ControlRequest
from sim.deploy import free_ports
from tests.helpers import frame_message, loopback_rig_config, loopback_sim_node

FPS = 10.0
PUPPET_SERIAL = 77
JPEG = b"\xff\xd8" + bytes(range(256)) + b"\xff\xd9"
REPLY_MAX_BYTES = 4096  # what an error reply may take, whatever the request held
HOUR_NS = 3600 * 10**9
_ESC = "\x1b"


def _frame(serial: int, index: int, seq: int, capture_ns: int, node: str = "puppet") -> list:
    return frame_message(node, serial, index, seq, capture_ns, JPEG).to_parts()


def _wait_until(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        time.sleep(0.05)


def _raw(endpoint: str, parts: list[bytes], timeout_ms: int = 5000) -> bytes | None:
    """Send ``parts`` as one request on a fresh REQ socket; the raw reply, or None."""
    sock = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        sock.send_multipart(parts)
        if not sock.poll(timeout_ms):
            return None
        return sock.recv()
    finally:
        sock.close(linger=0)


def _request(endpoint: str, verb: str, **args) -> ControlReply:
    raw = _raw(endpoint, [ControlRequest(verb=verb, args=args).to_bytes()])
    assert raw is not None, f"no reply to {verb} from {endpoint}"
    return ControlReply.from_bytes(raw)


class Puppet:
    """A test-driven agent: node ``puppet`` streams camera 77 at FPS with true stamps and
    answers ``status``; ``send(link, parts)`` publishes anything on ``puppet`` or ``open``."""

    def __init__(self) -> None:
        ctx = zmq.Context.instance()
        self.socks = {}
        self.endpoints = {}
        for name, kind in (("puppet", zmq.PUB), ("open", zmq.PUB), ("control", zmq.REP)):
            s = ctx.socket(kind)
            s.setsockopt(zmq.LINGER, 0)
            if kind == zmq.PUB:
                s.setsockopt(zmq.SNDHWM, 0)  # a flood waits in our queue, never dropped here
            port = s.bind_to_random_port("tcp://127.0.0.1")
            self.socks[name] = s
            self.endpoints[name] = f"tcp://127.0.0.1:{port}"
        self._inject: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="puppet", daemon=True)

    def start(self) -> Puppet:
        self._thread.start()
        return self

    def send(self, link: str, parts: list) -> None:
        self._inject.put((link, parts))

    def pending(self) -> int:
        return self._inject.qsize()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for s in self.socks.values():
            s.close(linger=0)

    def _run(self) -> None:  # the one thread that touches the sockets
        index = seq = 0
        next_frame = time.monotonic()
        info = {
            "camera_serial": PUPPET_SERIAL,
            "resolution": "TINY",
            "width": 8,
            "height": 4,
            "fps": FPS,
            "encoding": "jpeg",
            "factory_conf": None,
        }
        while not self._stop.is_set():
            if time.monotonic() >= next_frame:
                parts = _frame(PUPPET_SERIAL, index, seq, time.time_ns())
                self.socks["puppet"].send_multipart(parts)
                index, seq, next_frame = index + 1, seq + 1, next_frame + 1 / FPS
            rep = self.socks["control"]
            if rep.poll(0):
                req = ControlRequest.from_bytes(rep.recv())
                reply = ControlReply(
                    ok=True, result={"cameras_info": [info]}, request_id=req.request_id
                )
                rep.send(reply.to_bytes())
            for _ in range(500):
                try:
                    link, parts = self._inject.get_nowait()
                except queue.Empty:
                    break
                self.socks[link].send_multipart(parts)
            time.sleep(0.003)


def _node() -> NodeConfig:
    return loopback_sim_node(
        "node-a",
        fps=FPS,
        seed=4,
        cameras=({}, {}),
        where="hostile node.toml",
        status_interval_s=0.25,
    )


class Rig:
    def __init__(self, recorder: Recorder, agent: Agent, puppet: Puppet) -> None:
        self.recorder = recorder
        self.agent = agent
        self.puppet = puppet
        self.control = recorder.config.control_bind
        self.agent_control = agent.config.control_bind
        self.serials = tuple(w.serial for w in agent.workers)
        self.last_frames = 0

    def status(self) -> dict:
        reply = _request(self.control, "status")
        assert reply.ok, reply.error
        return reply.result

    def still_recording(self) -> dict:
        """The take goes on: the recorder answers, and more frames reach the file."""
        assert _request(self.control, "heartbeat").ok
        before = self.last_frames

        def grew():
            st = self.status()
            assert st["recording"], "the take stopped"
            return st if st["frames"] > before else None

        st = _wait_until(grew, 15, "frames to keep reaching the file")
        self.last_frames = st["frames"]
        return st


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    out = tmp_path_factory.mktemp("hostile")
    agent = Agent(_node())
    puppet = Puppet()
    (control,) = free_ports(1)
    (nobody,) = free_ports(1)
    config = RigConfig(
        rig_name="hostile",
        fps=FPS,
        control_bind=f"tcp://127.0.0.1:{control}",
        output_dir=str(out / "sessions"),
        agents=(
            AgentEndpoint(
                node_id="node-a",
                frames=agent.config.frames_bind,
                control=agent.config.control_bind,
                cameras=tuple(w.serial for w in agent.workers),
            ),
            AgentEndpoint(
                node_id="puppet",
                frames=puppet.endpoints["puppet"],
                control=puppet.endpoints["control"],
                cameras=(PUPPET_SERIAL,),
            ),
            AgentEndpoint(
                node_id="open",
                frames=puppet.endpoints["open"],
                control=f"tcp://127.0.0.1:{nobody}",
            ),
        ),
        require_ptp_lock=False,
        disk_reserve_gb=0.0,
        planned_duration_min=1.0,
        security=RigSecurityConfig(insecure=True),
        sealing=RigSealingConfig(plaintext=True),
    )
    recorder = Recorder(config)
    agent.start()
    puppet.start()
    recorder.start()
    r = Rig(recorder, agent, puppet)
    try:
        _wait_until(lambda: all(c["streaming"] for c in r.status()["cameras"]), 120, "every camera")
        reply = _request(r.control, "start", case="hostile-take", meta={"test": "hostile"})
        assert reply.ok, reply.error
        yield r
    finally:
        recorder.stop()
        agent.stop()
        puppet.close()


# -- control sockets: every request one bounded reply ---------------------------------------
_V2 = json.dumps(
    {"egosurg": "control", "version": 2, "verb": "status", "args": {}, "request_id": "abc"}
).encode()
_UNKNOWN_VERB = json.dumps(
    {"egosurg": "control", "version": 1, "verb": "format-disk", "args": {}, "request_id": "abc"}
).encode()
_NO_ID = json.dumps({"egosurg": "control", "version": 1, "verb": "status", "args": {}}).encode()
_HUGE_VERB = json.dumps(
    {"egosurg": "control", "version": 1, "verb": "x" * 1_000_000, "args": {}, "request_id": "a"}
).encode()
_LONG_ID = json.dumps(
    {"egosurg": "control", "version": 1, "verb": "status", "args": {}, "request_id": "i" * 5000}
).encode()
GARBAGE = {
    "5-byte hello": [b"hello"],
    "not UTF-8": [b"\xff\xfe\x00garbage\x80"],
    "version 2 envelope": [_V2],
    "unknown verb": [_UNKNOWN_VERB],
    "missing request_id": [_NO_ID],
    "a JSON list": [b"[1, 2, 3]"],
    "deep nesting": [b"[" * 100_000],
    "escape in the verb": [_UNKNOWN_VERB.replace(b"format-disk", b"\\u001b[2J")],
    "a 1 MB verb": [_HUGE_VERB],
    "a 5000-character request_id": [_LONG_ID],
    "two parts": [ControlRequest(verb="status").to_bytes(), b"second part"],
    "three empty parts": [b"", b"", b""],
    # JSON can spell half a UTF-16 pair, which no UTF-8 reply can echo
    "a lone surrogate as request_id": [_NO_ID[:-1] + b', "request_id": "\\ud800"}'],
}


def _check_error_reply(raw: bytes | None, what: str) -> ControlReply:
    assert raw is not None, f"{what}: no reply"
    assert len(raw) <= REPLY_MAX_BYTES, f"{what}: a {len(raw)}-byte reply echoes the input"
    reply = ControlReply.from_bytes(raw)
    assert not reply.ok and reply.error, what
    assert _ESC not in reply.error and "\u202e" not in reply.error, what
    return reply


def _control_counts(rig: Rig, daemon: str) -> dict:
    if daemon == "recorder":
        return rig.status()["control"]
    reply = _request(rig.agent_control, "status")
    assert reply.ok
    return reply.result["control"]


@pytest.mark.parametrize("daemon", ["recorder", "agent"])
def test_every_garbage_control_request_gets_one_bounded_error_and_is_counted(rig, daemon):
    """A 5-byte hello, a version-2 envelope, an unknown verb or a two-part request no longer
    ends the take or silences the agent: each gets an error reply that fits in a few KB."""
    endpoint = rig.control if daemon == "recorder" else rig.agent_control
    before = _control_counts(rig, daemon)
    for what, parts in GARBAGE.items():
        reply = _check_error_reply(_raw(endpoint, parts), what)
        if what in ("version 2 envelope", "unknown verb"):
            assert reply.request_id == "abc", f"{what}: the request's id is echoed"
        if what == "version 2 envelope":
            assert "version" in reply.error
        if what == "two parts":
            assert "2 parts" in reply.error
    after = _control_counts(rig, daemon)
    rejected = sum(after[k] - before[k] for k in ("rejected_malformed", "rejected_unknown_version"))
    assert rejected == len(GARBAGE)
    assert after["internal_errors"] == before["internal_errors"]
    # the daemon still answers a real request, and the take goes on
    assert _request(endpoint, "status").ok
    rig.still_recording()


def test_a_request_over_the_size_limit_is_refused_and_the_next_client_is_answered(rig):
    """A body above the control limit is dropped with its connection (MAXMSGSIZE) or
    refused; either way the recorder answers the next request."""
    body = b'{"egosurg": "control", "pad": "' + b"x" * (2 * MAX_JSON_BYTES) + b'"}'
    raw = _raw(rig.control, [body], timeout_ms=2000)
    if raw is not None:
        _check_error_reply(raw, "a 2 MB request")
    rig.still_recording()


# -- start arguments ------------------------------------------------------------------------
def _raw_start(args_json: str) -> bytes:
    return (
        '{"egosurg": "control", "version": 1, "verb": "start", "request_id": "s", "args": '
        + args_json
        + "}"
    ).encode()


HOSTILE_STARTS = {
    "a case name with a trailing newline": ({"case": "case-1\n"}, "case name"),
    "a JSON null case": ({"case": None}, "case name"),
    "520k backslashes as the case": ({"case": "\\" * 520_000}, "case name"),
    "a 900 KB metadata value": ({"case": "c", "meta": {"note": "v" * 900_000}}, "too long"),
    "a 100-character metadata key": ({"case": "c", "meta": {"k" * 100: "v"}}, "too long"),
    "65 metadata keys": ({"case": "c", "meta": {f"k{i}": "v" for i in range(65)}}, "65 keys"),
    "an ANSI escape in a key": ({"case": "c", "meta": {"a\x1b[2Jb": "v"}}, "\\x1b"),
    "a bidi override in a value": ({"case": "c", "meta": {"k": "abc\u202etxt"}}, "\\u202e"),
    "a C1 control in a value": ({"case": "c", "meta": {"k": "a\x9bb"}}, "\\x9b"),
    "a line break in a value": ({"case": "c", "meta": {"k": "a\nb"}}, "\\x0a"),
    "a number as metadata": ({"case": "c", "meta": {"k": 5}}, "key=value"),
    "a negative planned duration": ({"case": "c", "planned_duration_min": -5}, "> 0"),
    "a zero planned duration": ({"case": "c", "planned_duration_min": 0}, "> 0"),
    "planned duration as text": ({"case": "c", "planned_duration_min": "10"}, "> 0"),
    "planned duration true": ({"case": "c", "planned_duration_min": True}, "> 0"),
}


@pytest.mark.parametrize("what", list(HOSTILE_STARTS))
def test_hostile_start_arguments_are_refused_with_the_reason(rig, what):
    args, words = HOSTILE_STARTS[what]
    raw = _raw(rig.control, [_raw_start(json.dumps(args))])
    reply = _check_error_reply(raw, what)
    assert words in reply.error, reply.error
    assert "already recording" not in reply.error  # the arguments are checked first


def test_a_nan_or_infinite_planned_duration_is_refused(rig):
    """A NaN or infinite planned duration used to skip the disk check. JSON cannot say NaN, and
    1e999 (infinity once parsed) is refused as a request; the check itself refuses both."""
    reply = _check_error_reply(
        _raw(rig.control, [_raw_start('{"case": "c", "planned_duration_min": 1e999}')]), "inf"
    )
    assert "JSON" in reply.error
    default_min = rig.recorder.config.planned_duration_min
    for planned in (math.nan, math.inf, -math.inf):
        with pytest.raises(StartRefused, match="planned_duration_min"):
            start_args({"case": "c", "planned_duration_min": planned}, default_min)
    rig.still_recording()


# -- a rogue or broken publisher ------------------------------------------------------------
def test_a_rogue_publisher_cannot_grow_the_camera_table(rig):
    """6,000 made-up serials used to make the next status reply too large for its limit and the
    recorder exit; now they are refused and counted, and status stays small."""
    before = rig.status()["frames_refused_unknown_camera"]
    now = time.time_ns()
    for i in range(6000):
        rig.puppet.send("open", _frame(1_000_000 + i, 0, i, now, node="open"))
    _wait_until(
        lambda: rig.status()["frames_refused_unknown_camera"] - before == 6000,
        60,
        "6000 refusals",
    )
    raw = _raw(rig.control, [ControlRequest(verb="status").to_bytes()])
    assert raw is not None and len(raw) < 64 * 1024
    st = ControlReply.from_bytes(raw).result
    assert sorted(c["serial"] for c in st["cameras"]) == sorted((*rig.serials, PUPPET_SERIAL))
    assert len(rig.recorder.table.cameras) == 3
    rig.still_recording()


FORGED_INDEX = 10**9  # frame indices no real camera reaches in a test: found in the file if kept


def test_frames_forged_under_another_nodes_camera_are_refused(rig):
    """A link may speak only for the cameras rig.toml lists under its own node."""
    before = rig.status()["links"]["frames_refused_sender"]
    target = rig.serials[0]
    now = time.time_ns()
    for k in range(5):  # naming the real owner, from another agent's link
        rig.puppet.send("puppet", _frame(target, FORGED_INDEX + k, 0, now, node="node-a"))
    for k in range(5):  # naming itself, for a camera listed under node-a
        rig.puppet.send("open", _frame(target, FORGED_INDEX + 5 + k, 0, now, node="open"))
    _wait_until(
        lambda: rig.status()["links"]["frames_refused_sender"] - before == 10, 20, "refusals"
    )
    cams = {c["serial"]: c for c in rig.status()["cameras"]}
    assert cams[target]["node_id"] == "node-a"
    rig.still_recording()


def test_frames_stamped_hours_away_are_refused_and_counted_per_camera(rig):
    """One frame stamped far in the future used to make the synchroniser close hours of empty
    windows one by one; such stamps are now refused against the recorder's clock."""
    skew_s = rig.status()["max_clock_skew_s"]
    now = time.time_ns()
    stamps = [now + 8 * HOUR_NS, now - 8 * HOUR_NS, now + 365 * 24 * HOUR_NS]
    stamps.append(now + int(3 * skew_s * 1e9))
    for k, stamp in enumerate(stamps):
        rig.puppet.send("puppet", _frame(PUPPET_SERIAL, FORGED_INDEX + k, 10**6 + k, stamp))

    def refused():
        cams = {c["serial"]: c for c in rig.status()["cameras"]}
        return cams[PUPPET_SERIAL]["frames_refused_clock"] == len(stamps)

    _wait_until(refused, 20, "the refusals")
    st = rig.status()
    assert st["frames_refused_clock"] == len(stamps)
    sets = st["sets"]
    st = rig.still_recording()
    _wait_until(lambda: rig.status()["sets"] > sets, 15, "more synchronised sets")
    assert "stamped more than" in format_status(st)


def test_the_synchroniser_jumps_over_empty_time():
    """A frame stamped 8 hours (or 60 years) ahead costs one step, not a window per period, and
    the sets are those of the batch twin."""
    period = int(1e9 / 30)
    t0 = 1_700_000_000_000_000_000
    a = [t0 + i * period + 1_000 for i in range(40)] + [t0 + 8 * HOUR_NS]
    b = [t0 + i * period + 7_000 for i in range(40)] + [t0 + 8 * HOUR_NS + 3_000]
    b += [t0 + 8 * HOUR_NS + period + 2_000]
    result: dict[str, list] = {}

    def run() -> None:
        sync = Synchroniser(SyncConfig(camera_serials=(1, 2), fps=30))
        sets = []
        for i in range(max(len(a), len(b))):
            if i < len(a):
                sets += sync.add(1, a[i], i)
            if i < len(b):
                sets += sync.add(2, b[i], i)
        result["online"] = sets + sync.flush()
        far = Synchroniser(SyncConfig(camera_serials=(1, 2), fps=30))
        far.add(1, t0, 0)
        far.add(2, t0 + 10, 0)
        far.add(1, t0 + 60 * 365 * 24 * HOUR_NS, 1)
        result["far"] = far.flush()

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(timeout=20)
    assert not worker.is_alive(), "the synchroniser is closing empty windows one at a time"
    offline = group_offline({1: np.array(a), 2: np.array(b)}, 30)
    assert result["online"] == offline
    assert len(offline) == 42  # 40 sets, the far pair, and camera 2's last frame alone
    assert offline[40].members == (40, 40)
    assert offline[41].members == (None, 41)
    assert [s.members for s in result["far"]] == [(0, 0), (1, None)]


def test_the_recorder_keeps_no_message_per_camera(tmp_path):
    """Each camera's last message pinned its images (up to 128 MiB a serial); a frame's
    buffers are now free once it is handled."""
    recorder = Recorder(
        loopback_rig_config(tmp_path / "sessions", cameras=(11,), fps=FPS, rig_name="hand")
    )
    agent = recorder.config.agents[0]
    for k in range(3):
        left = np.frombuffer(JPEG, np.uint8).copy()
        right = np.frombuffer(JPEG, np.uint8).copy()
        header = _frame(11, k, k, time.time_ns(), node="n0")[0]
        recorder.on_published([header, left, right], agent)
        alive = weakref.ref(left)
        del left, right
        gc.collect()
        assert alive() is None, "the recorder holds the frame's image buffer"
    assert recorder.table.cameras[11].frames_rx == 3


def test_the_camera_table_is_capped_when_rig_toml_lists_no_cameras(tmp_path):
    recorder = Recorder(
        loopback_rig_config(tmp_path / "sessions", cameras=(), fps=FPS, rig_name="hand")
    )
    agent = recorder.config.agents[0]
    for serial in range(1, 101):
        recorder.on_published(_frame(serial, 0, serial, time.time_ns(), node="n0"), agent)
    assert len(recorder.table.cameras) == MAX_UNLISTED_CAMERAS
    st = recorder.status()
    assert st["frames_refused_unknown_camera"] == 100 - MAX_UNLISTED_CAMERAS
    assert len(st["cameras"]) == MAX_UNLISTED_CAMERAS
    assert len(json.dumps(st)) < 64 * 1024


# -- what the operator sees -----------------------------------------------------------------
def test_status_and_summary_print_remote_text_terminal_safe(rig):
    """A node id or reason with terminal escapes or bidi overrides is shown escaped."""
    st = rig.status()
    st["cameras"][0]["node_id"] = "evil\x1b[2J\u202e"
    st["agents"][0].update(node_id="evil\x1b]0;title\x07", alive=False)
    st["case"] = "case\x9b31m"
    printed = format_status(st)
    assert _ESC not in printed and "\u202e" not in printed and "\x9b" not in printed
    assert "evil\\x1b[2J\\u202e" in printed
    summary = {
        "case": "c\x1b[1m",
        "duration_s": 1.0,
        "sets": 1,
        "frames": 2,
        "bytes": 10,
        "file": "/x/\u202egpj.exe",
        "reason": "stopped\x1b[2J",
        "cameras": {"11\x1b": {k: 0 for k in ("frames", "dropped", "transport_lost")}},
    }
    for c in summary["cameras"].values():
        c.update(time_gaps=0, reconnects=0, missing_in_sets=0)
    printed = format_summary(summary)
    assert _ESC not in printed and "\u202e" not in printed


# -- progress, not liveness -----------------------------------------------------------------
def test_both_daemons_report_the_age_of_each_loops_progress(rig):
    ages = rig.status()["progress_age_s"]
    assert set(ages) == {"io"} and 0 <= ages["io"] < rig.status()["stall_limit_s"]
    reply = _request(rig.agent_control, "status")
    assert set(reply.result["progress_age_s"]) == {"publish", "control", "watchdog"}
    assert all(age < 5 for age in reply.result["progress_age_s"].values())


class Notifications:
    """Reads the datagrams sent to a real AF_UNIX socket, as systemd would, in a thread (the
    socket's queue holds only a few datagrams)."""

    def __init__(self) -> None:
        self.path = str(Path(tempfile.mkdtemp(prefix="egs-", dir="/tmp")) / "notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.1)
        self.got: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                self.got.append(self.sock.recv(4096).decode())
            except TimeoutError:
                pass

    def wait_for(self, until, timeout_s: float) -> list[str]:
        _wait_until(lambda: until(list(self.got)), timeout_s, f"a notification in {self.got}")
        return list(self.got)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()


def test_a_loop_that_stops_making_progress_stops_the_daemon_for_systemd(monkeypatch):
    """A thread alive but stuck is a stall: the watchdog pings stop and the daemon exits 1."""
    notes = Notifications()
    monkeypatch.setenv("NOTIFY_SOCKET", notes.path)
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    progress = Progress("io")
    hang, done = threading.Event(), threading.Event()

    def loop() -> None:
        while not done.is_set():
            if not hang.is_set():
                progress.beat("io")
            time.sleep(0.02)

    worker = threading.Thread(target=loop, daemon=True)
    timer = threading.Timer(1.0, hang.set)
    try:
        code = run_until_signal(
            lambda: (worker.start(), timer.start()),
            lambda: (done.set(), worker.join(timeout=5)),
            "toy daemon",
            progress=progress.ages_s,
            stall_limit_s=0.5,
        )
        assert code == 1
        got = notes.wait_for(lambda g: "STOPPING=1" in g, 5)
    finally:
        timer.cancel()
        notes.close()
    assert got[0].splitlines() == ["READY=1", "STATUS=toy daemon"]
    stalled = next(i for i, m in enumerate(got) if m.startswith("STATUS=stalled"))
    assert "no progress in io" in got[stalled]
    assert "WATCHDOG=1" in got[:stalled]
    assert "WATCHDOG=1" not in got[stalled:]


def test_the_recorder_process_speaks_the_systemd_notify_protocol(tmp_path):
    """A real ``egosurg recorder``: READY=1 once it answers, WATCHDOG=1 while its loop makes
    progress, a STATUS line, and STOPPING=1 then exit 0 on SIGTERM."""
    config = loopback_rig_config(tmp_path / "sessions", cameras=(), fps=10.0, rig_name="notify")
    rig_toml = tmp_path / "rig.toml"
    rig_toml.write_text(dumps(config))
    notes = Notifications()
    env = {"NOTIFY_SOCKET": notes.path, "WATCHDOG_USEC": "400000", "PATH": "/usr/bin:/bin"}
    log_path = tmp_path / "recorder.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "protocol.cli", "recorder", "--config", str(rig_toml)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=log_path.open("wb"),
    )
    try:
        got = notes.wait_for(lambda g: g.count("WATCHDOG=1") >= 3, 60)
        assert got[0].startswith("READY=1\nSTATUS=egosurg recorder notify")
        assert _request(config.control_bind, "heartbeat").ok
        notes.wait_for(lambda g: any(m.startswith("STATUS=idle") for m in g), 30)
        proc.send_signal(signal.SIGTERM)
        notes.wait_for(lambda g: "STOPPING=1" in g, 20)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        notes.close()
    assert "Traceback" not in log_path.read_text(errors="replace")


# -- the take survived ----------------------------------------------------------------------
def test_the_take_survived_every_attack_and_the_agent_still_serves_a_new_start(rig):
    """Stops the module's take: the file verifies, holds no forged or mis-stamped frame, and a
    new start (which asks the agent for status) goes through after the agent was attacked."""
    rig.still_recording()
    reply = _request(rig.control, "stop")
    assert reply.ok, reply.error
    summary = reply.result
    assert summary["frames"] > 0 and summary["sets"] > 0
    with SessionReader(summary["file"]) as r:
        assert r.verify() == []
        for s in (*rig.serials, PUPPET_SERIAL):
            indices = r.frame_table(s)["frame_index"]
            assert len(indices) > 0 and int(np.max(indices)) < FORGED_INDEX
        stamps = r.frame_table(PUPPET_SERIAL)["capture_unix_ns"]
        assert np.all(np.abs(stamps - time.time_ns()) < HOUR_NS)
    reply = _request(rig.control, "start", case="after-attacks")
    assert reply.ok, reply.error
    rig.last_frames = 0
    rig.still_recording()
    assert _request(rig.control, "stop").ok
    assert math.isfinite(summary["duration_s"])
