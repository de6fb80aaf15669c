"""Fuzzing, a bounded sample in the test pass (``bench/bench_fuzz.py`` runs 100k+ cases): what
arrives from the network or lies on a damaged disk is rejected with the project's named error,
never a crash or a hang, and the daemons answer every control request and keep serving.

The mutators and checks are ``tests/fuzzing.py``'s; hypothesis draws every choice, so a failure
shrinks to a small message or a single damaged offset."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from tests import fuzzing
from tests.fuzzing import DataChooser
from tests.helpers import loopback_rig_config, loopback_sim_node

# No example database (the test pass writes nothing into the checkout), and the same examples
# every run: a bounded sample must not pass or fail by chance; bench_fuzz.py explores seeds.
FAST = settings(max_examples=300, deadline=None, database=None, derandomize=True)
SOCKET = settings(
    max_examples=150,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
READ_LIMIT_S = 15.0  # the undamaged file reads in about 0.1 s


# -- decoders -----------------------------------------------------------------------------------
@FAST
@given(st.data())
def test_a_receiver_gets_a_message_or_a_malformed_error_from_any_published_parts(data):
    """Mutated frames (part counts, header fields, lengths, bodies) and status messages."""
    parts = fuzzing.frame_case(DataChooser(data))
    assert fuzzing.decode_frame_or_status(parts) in ("accepted", "rejected")


@FAST
@given(st.data())
def test_a_frame_with_any_header_field_changed_is_read_or_rejected(data):
    c = DataChooser(data)
    parts = fuzzing.valid_frame_parts(c)
    parts[0] = fuzzing.mutate_header(c, parts[0])
    assert fuzzing.decode_frame_or_status(parts) in ("accepted", "rejected")


@FAST
@given(st.data())
def test_any_agent_status_body_is_read_or_rejected(data):
    assert fuzzing.decode_control(fuzzing.status_case(DataChooser(data)), "status") in (
        "accepted",
        "rejected",
    )


@FAST
@given(st.data())
def test_any_control_request_or_reply_is_read_or_rejected(data):
    c = DataChooser(data)
    assert fuzzing.decode_control(fuzzing.control_case(c)[0], "request") in ("accepted", "rejected")
    assert fuzzing.decode_control(fuzzing.reply_case(c), "reply") in ("accepted", "rejected")


@FAST
@given(st.binary(max_size=300), st.sampled_from(["request", "reply", "status"]))
def test_random_bytes_are_rejected_by_every_json_decoder(raw, kind):
    assert fuzzing.decode_control(raw, kind) == "rejected"


# -- the daemons' control sockets -------------------------------------------------------------
@pytest.fixture(scope="module")
def recorder_control(tmp_path_factory):
    """A real recorder, its I/O thread running, plaintext links, no agent streaming."""
    from capture_agent.recorder.recorder import Recorder

    cfg = loopback_rig_config(tmp_path_factory.mktemp("fuzz-rec") / "sessions", rig_name="fuzz")
    recorder = Recorder(cfg)
    recorder.start()
    probe = fuzzing.ControlProbe(cfg.control_bind)
    try:
        yield recorder, probe
    finally:
        probe.close()
        recorder.stop()


@pytest.fixture(scope="module")
def agent_control():
    """A real agent with one simulated camera, plaintext links."""
    from capture_agent.agent.agent import Agent

    agent = Agent(loopback_sim_node("orin-f", fps=5.0, seed=2, where="fuzz node.toml"))
    agent.start()
    probe = fuzzing.ControlProbe(agent.config.control_bind)
    try:
        yield agent, probe
    finally:
        probe.close()
        agent.stop()


@SOCKET
@given(st.data())
def test_the_recorder_answers_every_control_request_once_and_keeps_serving(recorder_control, data):
    recorder, probe = recorder_control
    reply = probe.send(fuzzing.control_case(DataChooser(data)))
    assert reply.ok or reply.error
    assert recorder.take.recording is None  # no fuzzed start got a take going without cameras
    assert recorder.alive()


@SOCKET
@given(st.data())
def test_the_agent_answers_every_control_request_once_and_keeps_serving(agent_control, data):
    agent, probe = agent_control
    reply = probe.send(fuzzing.control_case(DataChooser(data)))
    assert reply.ok or reply.error
    assert all(t.is_alive() for t in agent._threads)


def test_the_hostile_requests_of_issue_24_are_answered(recorder_control, agent_control):
    """The exact inputs that used to stop the daemons: 'hello', a version-2 envelope, an unknown
    verb, two parts, a case of 520k backslashes."""
    from protocol.wire import MAX_JSON_BYTES

    hostile = [
        [b"hello"],
        [b'{"egosurg":"control","version":2,"verb":"status","args":{},"request_id":"x"}'],
        [b'{"egosurg":"control","version":1,"verb":"reboot","args":{},"request_id":"x"}'],
        [b"hello", b"world"],
        [
            b'{"egosurg":"control","version":1,"verb":"start","args":{"case":"'
            + b"\\\\" * 260_000
            + b'"},"request_id":"x"}'
        ],
    ]
    for _daemon, probe in (recorder_control, agent_control):
        for parts in hostile:
            reply = probe.send(parts)
            assert not reply.ok and len(reply.to_bytes()) < MAX_JSON_BYTES // 100


# -- the session reader on damaged files ------------------------------------------------------
class _Session:
    """The small session, its bytes and the reader's worker (a short repr: hypothesis prints
    its arguments when a case fails)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.original = path.read_bytes()
        self.live = fuzzing.live_ranges(self.original)
        self.worker = fuzzing.ReaderWorker()

    def read(self, data: bytes, name: str) -> dict:
        target = self.path.with_name(name)
        target.write_bytes(data)
        return self.worker.read(target, READ_LIMIT_S)

    def __repr__(self) -> str:
        return f"<session {self.path.name}, {len(self.original)} bytes>"


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    session = _Session(fuzzing.write_small_session(tmp_path_factory.mktemp("fuzz") / "fuzz.h5"))
    try:
        assert session.read(session.original, "copy.h5")["outcome"] == "accepted"  # it reads
        yield session
    finally:
        session.worker.close()


@settings(
    max_examples=120,
    deadline=None,
    database=None,
    derandomize=True,
    phases=[Phase.explicit, Phase.generate],  # shrinking a hang would rerun it for minutes
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.data())
def test_a_damaged_session_is_read_or_refused_with_a_session_format_error(small_session, data):
    """Truncated anywhere, bytes flipped or zeroed anywhere: the reader (in a child process,
    killed after READ_LIMIT_S) reads it or raises SessionFormatError, never hangs or crashes."""
    damaged, what = fuzzing.damage(DataChooser(data), small_session.original, small_session.live)
    result = small_session.read(damaged, "damaged.h5")
    assert result["outcome"] in ("accepted", "rejected"), f"{what}: {result}"


def test_a_damaged_global_heap_length_is_refused_without_hanging(small_session):
    """Found by bench_fuzz.py: the length of the variable-length string holding the summary
    JSON, cut from 24 to 15 bytes in HDF5's global heap, made opening the file hang in HDF5
    (reading the root attributes) for minutes."""
    original = small_session.original
    text = b'{"rejected_messages": 0}'
    at = original.index(text) - 8  # the heap object's 8-byte size field precedes its data
    assert int.from_bytes(original[at : at + 8], "little") == len(text)
    damaged = bytearray(original)
    damaged[at : at + 8] = (15).to_bytes(8, "little")
    result = small_session.read(bytes(damaged), "heap.h5")
    assert result["outcome"] in ("accepted", "rejected"), result
