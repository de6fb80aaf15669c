"""Only the rig's own keys get in: CURVE on every link, ZAP allow-lists, owner-only key files.

A real agent (sim camera) and a real recorder run in this process on loopback, each with its own
ZeroMQ context and authenticator; intruders are plain ZeroMQ sockets with keys of their own.
"""

from __future__ import annotations

import logging
import os
import pwd
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import zmq

from capture_agent.agent.agent import Agent
from capture_agent.operator.keys_cli import generate
from capture_agent.operator.rig_client import RigClient
from capture_agent.recorder.recorder import Recorder
from capture_agent.security import LinkSecurity
from protocol.errors import ConfigError
from protocol.formats.node_config import NodeConfig
from protocol.formats.rig_config import RigConfig
from protocol.wire import AgentStatus, ControlReply, ControlRequest, PtpState
from sim.deploy import free_ports
from tests.conftest import REPO, run_egosurg
from tests.helpers import frame_message

NODE = "orin-s"


def _rig_table(keys: Path, frames: str, control: str, cameras: list[int]) -> dict:
    return {
        "rig_name": "sec",
        "fps": 10,
        "control_bind": f"tcp://127.0.0.1:{free_ports(1)[0]}",
        "output_dir": str(keys.parent / "sessions"),
        "require_ptp_lock": False,
        "disk_reserve_gb": 0.0,
        "security": {
            "secret_key": "keys/recorder.key_secret",
            "operator_keys": ["keys/operator.key"],
            "operator_key": "keys/operator.key_secret",
        },
        "sealing": {"plaintext": True},  # sealed sessions: test_rig_sealing.py
        "agents": [
            {
                "node_id": NODE,
                "frames": frames,
                "control": control,
                "cameras": cameras,
                "public_key": f"keys/{NODE}.key",
            }
        ],
    }


@pytest.fixture(scope="module")
def keys(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("rig") / "keys"
    for name in ("recorder", "operator", NODE, "other-node", "intruder"):
        generate(d, name)
    return d


@pytest.fixture(scope="module")
def rig(keys):
    """A CURVE agent (one sim camera) and a CURVE recorder that records it."""
    fport, cport = free_ports(2)
    node = NodeConfig.from_table(
        {
            "node_id": NODE,
            "frames_bind": f"tcp://127.0.0.1:{fport}",
            "control_bind": f"tcp://127.0.0.1:{cport}",
            "status_interval_s": 0.25,
            "ptp": {"source": "none", "require_lock": False},
            "security": {
                "secret_key": f"keys/{NODE}.key_secret",
                "allowed_keys": ["keys/recorder.key", "keys/operator.key"],
            },
            "cameras": [
                {
                    "source": "sim",
                    "seed": 2,
                    "camera_index": 0,
                    "fps": 10.0,
                    "epoch_unix_ns": (time.time_ns() // 10**9 - 1) * 10**9,
                    "content_fps": 0.5,
                    "prerender_s": 2.0,
                    "pre_encode": "jpeg",
                    "drop_probability": 0.0,
                }
            ],
        },
        str(keys.parent / "node.toml"),
    )
    agent = Agent(node)
    agent.start()
    serial = agent.workers[0].serial
    cfg = RigConfig.from_table(
        _rig_table(keys, node.frames_bind, node.control_bind, [serial]),
        str(keys.parent / "rig.toml"),
    )
    recorder = Recorder(cfg)
    recorder.start()
    links = LinkSecurity.load(str(keys / "operator.key_secret"))
    client = RigClient(
        cfg.control_bind,
        links=links,
        recorder_key=recorder.links.security.public_key,
    )
    deadline = time.monotonic() + 120
    while not client.status()["cameras"][0]["streaming"]:
        assert time.monotonic() < deadline, "the CURVE agent never streamed to the recorder"
        time.sleep(0.3)
    try:
        yield agent, recorder, client, cfg
    finally:
        recorder.stop()
        agent.stop()


def _request(endpoint: str, server_key: bytes, key_file: Path | None) -> ControlReply | None:
    """One control request from a client with ``key_file``'s keys (None: plaintext)."""
    sock = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, 1500)
    # a REQ send waits for a connection: once the refused handshake has dropped it, there is
    # none (seen hanging a loaded CI run for 600 s), so the send is bounded too
    sock.setsockopt(zmq.SNDTIMEO, 1500)
    if key_file is not None:
        sock.curve_publickey, sock.curve_secretkey = zmq.auth.load_certificate(key_file)
        sock.curve_serverkey = server_key
    try:
        sock.connect(endpoint)
        sock.send(ControlRequest(verb="start", args={"case": "intruder"}).to_bytes())
        return ControlReply.from_bytes(sock.recv())
    except zmq.Again:
        return None
    finally:
        sock.close(linger=0)


def _frames_seen(endpoint: str, server_key: bytes | None, key_file: Path | None, s: float) -> int:
    sock = zmq.Context.instance().socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    if key_file is not None:
        sock.curve_publickey, sock.curve_secretkey = zmq.auth.load_certificate(key_file)
        sock.curve_serverkey = server_key
    n = 0
    deadline = time.monotonic() + s
    try:
        sock.connect(endpoint)
        while time.monotonic() < deadline:
            if sock.poll(100):
                sock.recv_multipart()
                n += 1
    finally:
        sock.close(linger=0)
    return n


def _wait_refused(guard, domain: str, at_least: int) -> int:
    deadline = time.monotonic() + 10
    while guard.refused.get(domain, 0) < at_least and time.monotonic() < deadline:
        time.sleep(0.05)
    return guard.refused.get(domain, 0)


def test_an_unlisted_key_and_a_plaintext_client_get_nothing_and_are_counted(rig, keys, caplog):
    """What the hospital relies on: a stranger on the VLAN can neither start a recording, nor
    ask the rig anything, nor watch the video; each attempt is in the log and in status."""
    agent, recorder, client, cfg = rig
    caplog.set_level(logging.WARNING, logger="capture_agent.security")
    intruder = keys / "intruder.key_secret"
    rec_key = recorder.links.security.public_key
    agent_key = zmq.auth.load_certificate(keys / f"{NODE}.key")[0]
    before_rec = recorder.links.guard.refused.get("recorder.control", 0)
    before_ctl = agent.guard.refused.get(f"{NODE}.control", 0)
    before_frames = agent.guard.refused.get(f"{NODE}.frames", 0)
    # the recorder's control socket: every command refused (no reply at all), nothing recorded
    assert _request(cfg.control_bind, rec_key, intruder) is None
    assert _request(cfg.control_bind, rec_key, None) is None
    assert _wait_refused(recorder.links.guard, "recorder.control", before_rec + 2) >= before_rec + 2
    # the agent's control and live video
    assert _request(cfg.agents[0].control, agent_key, intruder) is None
    assert _request(cfg.agents[0].control, agent_key, None) is None
    assert _frames_seen(cfg.agents[0].frames, agent_key, intruder, 1.0) == 0
    assert _frames_seen(cfg.agents[0].frames, None, None, 1.0) == 0
    assert _wait_refused(agent.guard, f"{NODE}.control", before_ctl + 2) >= before_ctl + 2
    assert _wait_refused(agent.guard, f"{NODE}.frames", before_frames + 2) >= before_frames + 2
    assert not list(Path(cfg.output_dir).glob("*.h5"))
    status = client.status()
    assert not status["recording"]
    assert status["links"]["auth_refused"]["recorder.control"] >= before_rec + 2
    # the agent reports its own refusals in its status reply, to the recorder's key
    reply = recorder.links.request(cfg.agents[0].control, "status")
    assert reply is not None and reply.ok, reply
    agent_links = reply.result["links"]["auth_refused"]
    assert agent_links[f"{NODE}.control"] >= before_ctl + 2
    assert agent_links[f"{NODE}.frames"] >= before_frames + 2
    intruder_public = zmq.auth.load_certificate(keys / "intruder.key")[0].decode()
    logged = caplog.text
    assert intruder_public in logged and "refused connection" in logged
    assert "handshake failed" in logged  # the plaintext attempts


def test_the_rig_keys_work_end_to_end(rig, keys):
    """The operator's key records a take from a CURVE agent through a CURVE recorder, and
    sees the live video."""
    agent, _, client, cfg = rig
    started = client.start("curve-take")
    time.sleep(1.5)
    summary = client.stop()
    assert summary["file"] == started["file"] and summary["frames"] > 5
    agent_key = zmq.auth.load_certificate(keys / f"{NODE}.key")[0]
    assert _frames_seen(cfg.agents[0].frames, agent_key, keys / "operator.key_secret", 1.0) > 0
    assert client.last_frame(agent.workers[0].serial).ndim == 3


def _publisher(key_file: Path | None) -> tuple[zmq.Socket, str]:
    pub = zmq.Context.instance().socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    if key_file is not None:
        pub.curve_publickey, pub.curve_secretkey = zmq.auth.load_certificate(key_file)
        pub.curve_server = True
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    return pub, f"tcp://127.0.0.1:{port}"


def _frame(node: str, serial: int, seq: int) -> list:
    now = time.time_ns()
    return frame_message(
        node, serial, seq, seq, now, bytes(12), encoding="raw_bgr8", size_px=(2, 2)
    ).to_parts()


def _status(node: str) -> list:
    return AgentStatus(
        node_id=node,
        sent_unix_ns=time.time_ns(),
        status_seq=1,
        ptp=PtpState(state="locked", master_offset_ns=0, gm_present=True),
        cameras=(),
        software_version="x",
    ).to_parts()


def _hand_driven_recorder(keys: Path, frames: str) -> Recorder:
    cfg = RigConfig.from_table(
        _rig_table(keys, frames, "tcp://127.0.0.1:1", [111]), str(keys.parent / "rig.toml")
    )
    recorder = Recorder(cfg)
    recorder.links.open()
    return recorder


def _pump(recorder: Recorder, pub: zmq.Socket, parts: list, seconds: float = 1.5) -> int:
    """Publish ``parts`` repeatedly for ``seconds`` (PUB/SUB joins late); messages received."""
    n = 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        pub.send_multipart(parts)
        n += recorder.receive_published(50)
    return n


def test_an_agent_key_cannot_speak_for_another_node_or_camera(keys):
    """A listed agent key that publishes another node's name, a camera rig.toml does not give
    it, or another node's status: refused and counted; its own camera is accepted."""
    pub, endpoint = _publisher(keys / f"{NODE}.key_secret")
    recorder = _hand_driven_recorder(keys, endpoint)
    table = recorder.table
    try:
        assert _pump(recorder, pub, _frame("orin-x", 111, 0)) > 0
        assert table.frames_refused_sender > 0 and 111 not in table.cameras
        refused = table.frames_refused_sender
        assert _pump(recorder, pub, _frame(NODE, 222, 0)) > 0
        assert table.frames_refused_sender > refused and 222 not in table.cameras
        assert _pump(recorder, pub, _status("orin-x")) > 0
        assert table.status_refused_sender > 0 and "orin-x" not in table.agent_status
        assert _pump(recorder, pub, _frame(NODE, 111, 0)) > 0
        assert 111 in table.cameras  # its own camera, from its own key
        assert recorder.status()["links"]["frames_refused_sender"] >= 2
    finally:
        recorder.links.close()
        pub.close(linger=0)


@pytest.mark.parametrize("key", ["other-node", None])
def test_a_publisher_without_the_agents_key_delivers_nothing(keys, key):
    """A rogue publisher at an agent's address (another key, or plaintext) gets no message
    into the recorder: the recorder's SUB only completes a handshake with the agent's key."""
    pub, endpoint = _publisher(keys / f"{key}.key_secret" if key else None)
    recorder = _hand_driven_recorder(keys, endpoint)
    try:
        assert _pump(recorder, pub, _frame(NODE, 111, 0), seconds=1.5) == 0
        assert not recorder.table.cameras
    finally:
        recorder.links.close()
        pub.close(linger=0)


def test_keys_generate_makes_owner_only_files_and_never_overwrites(tmp_path):
    out = tmp_path / "new" / "keys"
    done = run_egosurg("keys", "generate", "--out", str(out), "--name", "recorder")
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    assert stat.S_IMODE((out / "recorder.key_secret").stat().st_mode) == 0o600
    public, secret = zmq.auth.load_certificate(out / "recorder.key_secret")
    assert secret is not None and zmq.curve_public(secret) == public
    assert zmq.auth.load_certificate(out / "recorder.key") == (public, None)
    before = (out / "recorder.key_secret").read_bytes()
    again = run_egosurg("keys", "generate", "--out", str(out), "--name", "recorder")
    assert again.returncode == 2 and "Traceback" not in again.stderr
    assert "exists" in again.stderr
    assert (out / "recorder.key_secret").read_bytes() == before
    shown = run_egosurg("keys", "show", str(out / "recorder.key"))
    assert shown.returncode == 0 and public.decode() in shown.stdout


def test_a_secret_key_others_can_read_is_refused(tmp_path):
    _, secret = generate(tmp_path / "keys", "orin-a")
    os.chmod(secret, 0o640)
    with pytest.raises(ConfigError) as info:
        LinkSecurity.load(str(secret))
    assert str(secret) in str(info.value) and "chmod 600" in str(info.value)
    node = tmp_path / "node.toml"
    node.write_text(
        'node_id = "orin-a"\nframes_bind = "tcp://127.0.0.1:1"\ncontrol_bind = '
        '"tcp://127.0.0.1:2"\n[security]\nsecret_key = "keys/orin-a.key_secret"\n'
        'allowed_keys = ["keys/orin-a.key"]\n[[cameras]]\nsource = "video"\npath = "none.mp4"\n'
        "serial = 5\n"
    )
    out = run_egosurg("agent", "--config", str(node), timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "chmod 600" in out.stderr


def _has_user(name: str) -> bool:
    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True


def _as_nobody(argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    nobody = pwd.getpwnam("nobody")
    drop = ["setpriv", f"--reuid={nobody.pw_uid}", f"--regid={nobody.pw_gid}", "--clear-groups"]
    env = {**os.environ, "HOME": "/"}
    return subprocess.run(
        drop + argv, capture_output=True, text=True, timeout=120, cwd=cwd, env=env
    )


@pytest.mark.skipif(
    os.geteuid() != 0 or not _has_user("nobody") or shutil.which("setpriv") is None,
    reason="needs root, the user 'nobody' and setpriv (util-linux) to act as the service user",
)
def test_keys_for_the_service_user_and_an_unreadable_key_is_one_line():
    """``sudo egosurg keys generate --owner USER``: USER reads its secret; keys root kept are
    refused in one line that names the file and the fix (exit 2), never a traceback."""
    base = Path(tempfile.mkdtemp(prefix="egosurg-keys-"))  # not tmp_path: its parents are 0700
    try:
        base.chmod(0o755)
        done = run_egosurg(
            "keys", "generate", "--owner", "nobody", "--out", str(base / "keys"), "--name", "orin-a"
        )
        assert done.returncode == 0 and "owned by nobody" in done.stdout, done.stderr
        nobody = pwd.getpwnam("nobody").pw_uid
        for p in (base / "keys", base / "keys" / "orin-a.key_secret"):
            assert p.stat().st_uid == nobody and stat.S_IMODE(p.stat().st_mode) in (0o700, 0o600)
        read = "from capture_agent.security import load_keypair as k; k('keys/orin-a.key_secret')"
        out = _as_nobody([sys.executable, "-c", read], cwd=base)
        assert out.returncode == 0, out.stderr
        generate(base / "root-keys", "orin-a")  # as root, without --owner: what went wrong
        (base / "root-keys").chmod(0o755)  # the file itself, not only its folder, is unreadable
        node = base / "node.toml"
        node.write_text(
            'node_id = "orin-a"\nframes_bind = "tcp://127.0.0.1:1"\ncontrol_bind = '
            '"tcp://127.0.0.1:2"\n[security]\nsecret_key = "root-keys/orin-a.key_secret"\n'
            'allowed_keys = ["root-keys/orin-a.key"]\n[ptp]\nsource = "none"\n[[cameras]]\n'
            'source = "video"\npath = "none.mp4"\nserial = 5\n'
        )
        node.chmod(0o644)
        agent = [sys.executable, "-m", "protocol.cli", "agent", "--config", str(node)]
        out = _as_nobody(agent, cwd=REPO)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "root-keys/orin-a.key_secret" in lines[0], out.stderr
        assert "cannot be read by user nobody" in lines[0] and "--owner nobody" in lines[0]
        refused = run_egosurg("keys", "generate", "--owner", "no-such-user-x", "--out",
                              str(base / "k3"), "--name", "a")  # fmt: skip
        assert refused.returncode == 2 and "no such user" in refused.stderr
        assert not (base / "k3").exists()
    finally:
        shutil.rmtree(base)


NODE_BASE = {
    "node_id": "orin-a",
    "frames_bind": "tcp://10.0.0.1:5550",
    "control_bind": "tcp://10.0.0.1:5551",
    "cameras": [{"source": "sim"}],
}


@pytest.mark.parametrize(
    ("security", "change", "words"),
    [
        (None, {}, ["egosurg keys generate", "insecure = true"]),
        ({"secret_key": "a.key_secret"}, {}, ["allowed_keys", "egosurg keys generate"]),
        ({"insecure": "yes"}, {}, ["insecure", "bool"]),
        ({"secret_key": "a", "allowed_keys": ["b"], "typo": 1}, {}, ["typo"]),
        (
            {"secret_key": "a", "allowed_keys": ["b"]},
            {"frames_bind": "tcp://*:5550"},
            ["every interface", "allow_all_interfaces"],
        ),
        (
            {"secret_key": "a", "allowed_keys": ["b"]},
            {"control_bind": "tcp://0.0.0.0:5551"},
            ["every interface"],
        ),
    ],
)
def test_a_node_config_without_keys_says_what_to_do(security, change, words):
    table = {**NODE_BASE, **change}
    if security is not None:
        table["security"] = security
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_table(table, "node.toml")
    for w in words:
        assert w in str(info.value)


def test_binding_every_interface_needs_saying_so():
    for security in ({"insecure": True}, {"secret_key": "a", "allowed_keys": ["b"]}):
        allow = {**security, "allow_all_interfaces": True}
        cfg = NodeConfig.from_table(
            {**NODE_BASE, "frames_bind": "tcp://*:5550", "security": allow}, "/etc/node.toml"
        )
        assert cfg.frames_bind == "tcp://*:5550"
    assert cfg.security.secret_key == "/etc/a"  # relative to the config's folder


def test_a_rig_config_needs_every_agents_key(keys):
    table = _rig_table(keys, "tcp://127.0.0.1:1", "tcp://127.0.0.1:2", [1])
    del table["agents"][0]["public_key"]
    with pytest.raises(ConfigError, match="public_key"):
        RigConfig.from_table(table, "rig.toml")
    table = _rig_table(keys, "tcp://127.0.0.1:1", "tcp://127.0.0.1:2", [1])
    table["security"] = {}
    with pytest.raises(ConfigError, match="egosurg keys generate"):
        RigConfig.from_table(table, "rig.toml")
    table["receive_buffer_mb"] = 10.0  # under 8 of the largest legal frame messages
    table["security"] = {"insecure": True}
    with pytest.raises(ConfigError, match="receive_buffer_mb"):
        RigConfig.from_table(table, "rig.toml")


def test_insecure_links_warn_at_every_start(keys, caplog):
    for _ in range(2):
        table = _rig_table(keys, "tcp://127.0.0.1:1", "tcp://127.0.0.1:2", [1])  # a new port
        table["security"] = {"insecure": True}
        cfg = RigConfig.from_table(table, str(keys.parent / "rig.toml"))
        caplog.clear()
        recorder = Recorder(cfg)
        recorder.links.open()
        recorder.links.close()
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert any("INSECURE" in r.getMessage() for r in warnings)


def test_a_client_without_keys_is_told_how_to_get_them(monkeypatch):
    for name in ("EGOSURG_KEY", "EGOSURG_RECORDER_KEY", "EGOSURG_INSECURE"):
        monkeypatch.delenv(name, raising=False)
    out = run_egosurg("status", "--recorder", "tcp://127.0.0.1:9", timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "egosurg keys generate" in out.stderr and "EGOSURG_KEY" in out.stderr
