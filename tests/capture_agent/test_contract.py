"""The agent-recorder contract (docs/capture.md, "Writing an agent") is enough to write an agent.

``spec_agent.py`` (beside this file) was written from the documents alone, for a camera
EgoSurg does not know (64x48 JPEGs, mode "TEST64x48", no factory file). Against a real recorder
(in this process, real sockets on loopback) and the real ``egosurg record`` command, it records a
take that holds exactly the frames it sent; every broken field of its ``status`` reply is refused
with the field's name, and an agent's own refusal is reported as its error, not as "is it running?".
"""

from __future__ import annotations

import inspect
import os
import pydoc
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq.auth
from hypothesis import given, settings
from hypothesis import strategies as st

from capture_agent.errors import CommandRefusedError
from capture_agent.operator.console import Rig, namespace
from capture_agent.operator.keys_cli import generate
from capture_agent.operator.rig_client import RigClient
from capture_agent.recorder.recorder import Recorder
from protocol.formats.rig_config import RigConfig
from protocol.sealing import generate_identity, load_identity, write_identity
from protocol.session import SessionReader
from protocol.wire.agent_info import AgentReplyError, AgentStatusReply
from sim.deploy import free_ports
from tests.capture_agent.spec_agent import SpecAgent
from tests.conftest import run_egosurg

NODE = "spec-node"
SERIALS = (7001, 7002)
DOC = "docs/capture.md#the-status-reply"


def _rig_toml(directory: Path, recorder_port: int, frames: int, control: int) -> Path:
    path = directory / "rig.toml"
    path.write_text(
        f"""rig_name = "contract"
fps = 15
control_bind = "tcp://127.0.0.1:{recorder_port}"
output_dir = "{directory / "sessions"}"
disk_reserve_gb = 0
planned_duration_min = 1

[security]
secret_key = "keys/recorder.key_secret"
operator_keys = ["keys/operator.key"]
operator_key = "keys/operator.key_secret"

[sealing]
recipients = ["keys/contract-site.recipient"]

[[agents]]
node_id = "{NODE}"
frames = "tcp://127.0.0.1:{frames}"
control = "tcp://127.0.0.1:{control}"
cameras = [{", ".join(map(str, SERIALS))}]
public_key = "keys/spec-agent.key"
"""
    )
    return path


def _reader(session: str) -> SessionReader:
    """A session the contract rig recorded, opened with its site identity."""
    identity = Path(session).parent.parent / "reader-keys" / "contract-site.identity"
    return SessionReader(session, identity=load_identity(identity))


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The spec agent streaming two cameras to a recorder, every link CURVE: the agent admits
    the recorder's and the operator's keys, the recorder knows the agent's."""
    directory = tmp_path_factory.mktemp("contract")
    for name in ("recorder", "operator", "spec-agent"):
        generate(directory / "keys", name)
    # the sessions are sealed for a site key whose identity only the readers below hold
    public, _ = write_identity(generate_identity("contract-site"), directory / "reader-keys")
    (directory / "keys" / public.name).write_text(public.read_text())
    certificate = zmq.auth.load_certificate
    allowed = tuple(
        certificate(directory / "keys" / f"{n}.key")[0] for n in ("recorder", "operator")
    )
    recorder_port, frames, control = free_ports(3)
    agent = SpecAgent(
        node_id=NODE,
        serials=SERIALS,
        frames_bind=f"tcp://127.0.0.1:{frames}",
        control_bind=f"tcp://127.0.0.1:{control}",
        keypair=certificate(directory / "keys" / "spec-agent.key_secret"),
        allowed_client_keys=allowed,
    ).start()
    rig_toml = _rig_toml(directory, recorder_port, frames, control)
    recorder = Recorder(RigConfig.from_toml(rig_toml))
    recorder.start()
    client = RigClient.connect(config=str(rig_toml))
    try:
        deadline = time.monotonic() + 20.0
        while True:
            st = client.status()
            if all(c["streaming"] for c in st["cameras"]) and all(a["alive"] for a in st["agents"]):
                break
            assert time.monotonic() < deadline, f"the spec agent never streamed: {st}"
            time.sleep(0.2)
        yield agent, client, rig_toml
    finally:
        recorder.stop()
        agent.stop()


@pytest.fixture
def agent(rig):
    """The rig's agent, its answers restored after each test."""
    spec_agent, _, _ = rig
    yield spec_agent
    spec_agent.status_result = None
    spec_agent.status_refusal = None
    spec_agent.status_delay_s = 0.0


def _refusal(client: RigClient) -> str:
    with pytest.raises(CommandRefusedError) as info:
        client.start("refused-case")
    return str(info.value)


def test_an_agent_written_from_the_contract_records_a_take(rig, agent):
    """A third party's agent starts, records and stops a take with `egosurg record`; the
    session holds exactly the frames it sent, byte for byte, under the camera mode it declared."""
    _, client, rig_toml = rig
    out = run_egosurg("record", "start", "--case", "spec-take", "--config", str(rig_toml))
    assert out.returncode == 0, out.stderr
    assert "recording case spec-take from 2 cameras" in out.stdout
    time.sleep(2.0)
    out = run_egosurg("record", "stop", "--config", str(rig_toml), "--json")
    assert out.returncode == 0, out.stderr
    summary = client.status()["last_recording"]
    sent = agent.frames_sent()
    with _reader(summary["file"]) as reader:
        assert reader.sealed and reader.info.closed_cleanly
        assert reader.verify() == []
        assert reader.gaps() == []  # nothing lost, no reconnect
        for serial in SERIALS:
            info = reader.info.camera(serial)
            assert (info.node_id, info.resolution, info.width, info.height) == (
                NODE, "TEST64x48", 64, 48
            )  # fmt: skip
            assert (info.fps_nominal, info.encoding, info.factory_conf_text) == (15.0, "jpeg", "")
            table = reader.frame_table(serial)
            index, capture = table["frame_index"].tolist(), table["capture_unix_ns"].tolist()
            stored = list(zip(index, capture, strict=True))
            assert len(stored) >= 15  # two seconds at 15 fps, less the start and the stop
            first = sent[serial].index(stored[0])
            assert stored == sent[serial][first : first + len(stored)]  # exactly, in order
            left, right = reader.frame_bytes(serial, len(stored) // 2)
            assert (left, right) == agent._images[serial]
            assert summary["cameras"][str(serial)]["frames"] == len(stored)
            assert summary["cameras"][str(serial)]["dropped"] == 0


def test_the_spec_agent_uses_no_egosurg_code():
    """The proof holds only while the spec agent is built from the documents, not our code."""
    import ast

    tree = ast.parse((Path(__file__).parent / "spec_agent.py").read_text())
    imported = {
        alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
        for alias in node.names
    } | {
        node.module.split(".")[0] for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module
    }  # fmt: skip
    assert not imported & {"protocol", "capture_agent", "sim", "tests", "calibration"}
    assert imported <= {"__future__", "json", "struct", "threading", "time", "collections",
                        "dataclasses", "typing", "cv2", "numpy", "zmq"}  # fmt: skip


@pytest.mark.parametrize(
    "field",
    ["camera_serial", "resolution", "width", "height", "fps", "encoding", "factory_conf"],
)
def test_each_missing_cameras_info_field_is_named(rig, agent, field):
    """The recorder says which field an agent's status reply lacks, and where the rule is."""
    _, client, _ = rig

    def without(result):
        del result["cameras_info"][0][field]
        return result

    agent.status_result = without
    message = _refusal(client)
    assert f"agent {NODE}'s status reply lacks cameras_info[0].{field}; see {DOC}" in message
    assert "internal error" not in message


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("camera_serial", "7001", "an integer"),
        ("camera_serial", 0, "an integer from 1"),
        ("resolution", 1200, "a mode name"),
        ("resolution", "HD 1200\x1b[2J", "a mode name"),
        ("resolution", "HD1200", "1920x1200"),  # a ZED X mode must have its size
        ("width", "64", "an integer from 1 to 8192"),
        ("height", 0, "an integer from 1 to 8192"),
        ("fps", "fast", "a number above 0"),
        ("fps", 0, "a number above 0"),
        ("encoding", "png", '"jpeg" or "raw_bgr8"'),
        ("resolution", "SVGA\n", "a mode name"),
        ("encoding", ["jpeg"], '"jpeg" or "raw_bgr8"'),
        ("factory_conf", 3, "the factory file's text, or null"),
        ("factory_conf", "[STEREO]\0", "no NUL characters"),
        ("factory_conf", "x" * 70_000, "65536-byte limit"),
    ],
)
def test_each_mistyped_cameras_info_field_is_named(rig, agent, field, value, words):
    """A wrong value is refused with the field, the value (escaped, bounded) and the rule."""
    _, client, _ = rig

    def wrong(result):
        result["cameras_info"][1][field] = value
        return result

    agent.status_result = wrong
    message = _refusal(client)
    assert f"agent {NODE}'s status reply" in message
    assert f"cameras_info[1].{field}" in message or f"cameras_info[1].{field[:5]}" in message
    assert words in message
    assert "\x1b" not in message and len(message) < 400


def test_a_reply_with_a_lone_surrogate_is_refused_as_not_utf8(rig, agent):
    """JSON can spell a half UTF-16 pair (a lone surrogate) that no UTF-8 text holds: the whole
    reply is refused as unreadable, in one bounded line, before any field is trusted."""
    _, client, _ = rig

    def wrong(result):
        result["cameras_info"][1]["factory_conf"] = "\ud800"
        return result

    agent.status_result = wrong
    message = _refusal(client)
    low = message.lower()
    assert NODE in message and ("surrogate" in low or "utf-8" in low), message
    assert len(message) < 400


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda r: {"status": r["status"]}, "lacks cameras_info"),
        (lambda r: {**r, "cameras_info": r["cameras_info"][:1]}, "no cameras_info entry for"),
        (
            lambda r: {**r, "cameras_info": r["cameras_info"] + r["cameras_info"][:1]},
            "lists camera 7001 twice",
        ),
        (lambda r: {**r, "status": {**r["status"], "node_id": "other-node"}}, "status.node_id"),
        (lambda r: {**r, "status": {**r["status"], "ptp": {}}}, "lacks status.ptp"),
    ],
)
def test_a_reply_that_breaks_the_contract_elsewhere_is_named(rig, agent, change, words):
    """Missing list, a camera rig.toml expects, a duplicate, another node's status: each named."""
    _, client, _ = rig
    agent.status_result = change
    message = _refusal(client)
    assert f"agent {NODE}'s status reply" in message and words in message


def test_an_agent_that_refuses_status_is_reported_with_its_own_error(rig, agent):
    """ok:false is the agent's answer, not silence: its error reaches the operator."""
    _, client, _ = rig
    agent.status_refusal = "camera SN7001 is overheating; let it cool for 10 minutes"
    message = _refusal(client)
    assert message == (
        f"agent {NODE} refused 'status': camera SN7001 is overheating; let it cool for 10 minutes"
    )
    assert "is it running" not in message


def test_an_agent_that_does_not_answer_is_asked_whether_it_runs(rig, agent):
    """No reply within the recorder's timeout: the operator is asked to check the agent."""
    _, client, _ = rig
    agent.status_delay_s = 2.0
    message = _refusal(client)
    assert f"agent {NODE} does not answer" in message and "is it running" in message


def test_the_cli_prints_the_contract_problem_in_one_line(rig, agent):
    """`egosurg record start` prints the named field, exit code 2, no traceback."""
    _, _, rig_toml = rig

    def without(result):
        del result["cameras_info"][0]["resolution"]
        return result

    agent.status_result = without
    out = run_egosurg("record", "start", "--case", "c1", "--config", str(rig_toml))
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert "Traceback" not in out.stderr and "internal error" not in out.stderr
    assert (
        f"egosurg record: error: agent {NODE}'s status reply lacks cameras_info[0].resolution; "
        f"see {DOC}"
    ) in out.stderr


# no subnormal floats: importing reconstructor/ (another test, same process) flushes denormals to
# zero on the CPU, and hypothesis then refuses to draw them
_JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_subnormal=False)
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=8,
)


def _valid_result() -> dict:
    agent = SpecAgent(node_id=NODE, serials=SERIALS, frames_bind="", control_bind="")
    try:
        return {"cameras_info": agent._cameras_info(), "status": agent._status_body(1)}
    finally:
        agent._ctx.term()


@settings(max_examples=300, deadline=None)
@given(
    entry=st.integers(0, 1),
    key=st.sampled_from(
        ["camera_serial", "resolution", "width", "height", "fps", "encoding", "factory_conf", "x"]
    ),
    value=_JSON,
    drop=st.booleans(),
)
def test_any_broken_entry_is_refused_by_name_or_accepted_whole(entry, key, value, drop):
    """Whatever an agent puts in an entry, the check ends in a valid reply or an error naming
    the field: never a KeyError or TypeError (what once became 'internal error: ...')."""
    result = _valid_result()
    if drop:
        result["cameras_info"][entry].pop(key, None)
    else:
        result["cameras_info"][entry][key] = value
    try:
        reply = AgentStatusReply.from_json(result, node_id=NODE)
    except AgentReplyError as exc:
        # the changed entry, or the other one when the change duplicates its serial
        assert exc.field.startswith("cameras_info[") and exc.field in str(exc)
    else:  # accepted: then the entry holds exactly what was sent (or the key was extra)
        info = reply.cameras_info[entry]
        if key != "x" and not drop:
            assert getattr(info, key) == ("" if value is None else value)
        assert reply.cameras_info[1 - entry].to_json() == {
            **result["cameras_info"][1 - entry],
            "factory_conf": "",
        }


@settings(max_examples=200, deadline=None)
@given(result=_JSON)
def test_any_json_is_refused_by_name_or_accepted(result):
    """A reply of any shape is refused with a named field, never with another exception."""
    try:
        AgentStatusReply.from_json(result, node_id=NODE)
    except AgentReplyError as exc:
        assert exc.field and exc.field in str(exc)


# -- the operator console says what the CLI says ---------------------------------------------


def test_the_console_starts_and_stops_in_the_words_of_the_cli(rig, agent):
    """rig.start() answers as `egosurg record start` does; rig.stop() shows the stop summary;
    refusals show the one-line reason and are false, so `if rig.start(...)` reads right."""
    _, client, _ = rig
    console = namespace(client)["rig"]
    started = console.start("console-case", surgeon="A. Smith")
    file = client.status()["file"]
    assert repr(started) == f"recording case console-case from 2 cameras to {file}"
    again = console.start("second-case")
    assert not again and repr(again).startswith("rig.start: refused: already recording")
    time.sleep(1.0)
    summary = console.stop()
    assert repr(summary).startswith("case console-case: ") and f"file: {file}" in repr(summary)
    nothing = console.stop()
    assert not nothing and "\n" not in repr(nothing)
    assert repr(nothing).startswith("rig.stop: refused: ") and "nothing to stop" in repr(nothing)
    with _reader(file) as reader:
        assert reader.info.case_metadata == {"surgeon": "A. Smith"}


def test_the_console_reports_a_refused_start_in_one_line(rig, agent):
    """An agent's refusal reaches the console as the recorder's one-line reason."""
    _, client, _ = rig
    agent.status_refusal = "camera SN7001 is overheating"
    answer = Rig(client).start("hot-case")
    assert repr(answer) == (
        f"rig.start: refused: agent {NODE} refused 'status': camera SN7001 is overheating"
    )


def test_the_console_without_a_recorder_says_so(rig):
    """No recorder at the address: the console says which address and what to check."""
    _, _, rig_toml = rig
    port = free_ports(1)[0]
    lost = Rig(RigClient(f"tcp://127.0.0.1:{port}", timeout_s=0.5, config=str(rig_toml)))
    answer = lost.status()
    assert not answer and repr(answer).startswith("rig.status: refused: no recorder answered at")


def test_the_console_shows_live_images(rig, agent, tmp_path, capsys):
    """rig.last_frame gives the camera's image; an unknown camera is refused by name. A saved
    frame is a plaintext picture of the room: owner-only whatever the umask, and said so."""
    _, client, _ = rig
    console = Rig(client)
    image = console.last_frame(SERIALS[0], side="right")
    assert image.shape == (48, 64, 3)
    old_umask = os.umask(0o022)
    try:
        saved = console.save_frame(SERIALS[1], str(tmp_path / "f.png"))
    finally:
        os.umask(old_umask)
    assert saved == str(tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 0
    assert (tmp_path / "f.png").stat().st_mode & 0o077 == 0
    assert "wrote plaintext a live frame" in capsys.readouterr().err
    unknown = console.last_frame(99)
    assert not unknown and "camera 99 is not streaming" in repr(unknown)


def test_the_live_view_of_a_sealed_rig_writes_no_frame_to_disk(rig, agent, tmp_path, monkeypatch):
    """During a sealed take, rig.last_frame shows each camera's image as sent (over its CURVE
    link), and no file of the rig or of the console's folder holds a frame in the clear: the
    live view keeps frames in memory and the take stores them sealed (docs/capture.md)."""
    _, client, rig_toml = rig
    monkeypatch.chdir(tmp_path)  # where a console would write, if it wrote anything
    console = Rig(client)
    client.start("live-view-case")
    try:
        time.sleep(0.5)
        for serial in SERIALS:
            sent = cv2.imdecode(np.frombuffer(agent._images[serial][0], np.uint8), cv2.IMREAD_COLOR)
            assert np.array_equal(console.last_frame(serial), sent)
    finally:
        summary = client.stop()
    files = [p for root in (rig_toml.parent, tmp_path) for p in root.rglob("*") if p.is_file()]
    assert Path(summary["file"]) in files and summary["cameras"][str(SERIALS[0])]["frames"] > 0
    images = [agent._images[serial][k] for serial in SERIALS for k in (0, 1)]
    assert [str(p) for p in files if any(image in p.read_bytes() for image in images)] == []


def test_every_console_command_explains_itself_in_help():
    """help(rig) shows what each command does."""
    commands = [n for n, f in inspect.getmembers(Rig, inspect.isfunction) if not n.startswith("_")]
    assert set(commands) >= {"status", "start", "stop", "last_frame", "save_frame"}
    text = pydoc.render_doc(Rig, renderer=pydoc.plaintext)
    for name in commands:
        doc = inspect.getdoc(getattr(Rig, name))
        assert doc and len(doc) > 40, name
        assert doc.splitlines()[0] in text
