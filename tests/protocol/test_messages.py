"""The wire contract of protocol/wire/__init__.py, over real ZeroMQ sockets on loopback."""

from __future__ import annotations

import json
import random
import struct
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zmq

from protocol.errors import UserError
from protocol.wire import (
    CONTROL_VERBS,
    MAX_FRAME_BYTES,
    AgentStatus,
    CameraStatus,
    ControlReply,
    ControlRequest,
    Encoding,
    FrameMessage,
    MalformedMessageError,
    PtpState,
    UnknownVersionError,
    decode_published,
)

TIMEOUT_MS = 2000
# The header layout as the module docstring documents it, written out independently here.
DOC_HEADER = struct.Struct("<4sHHQQQqqqQQHHBBBB32s")
OFF_VERSION, OFF_HEADER_BYTES, OFF_FRAME_INDEX = 4, 6, 24
OFF_LEFT_BYTES, OFF_WIDTH, OFF_ENCODING, OFF_NODE_LEN, OFF_NODE = 56, 72, 76, 78, 80


# ---------------------------------------------------------------------------------------------
# sockets


@pytest.fixture
def ctx() -> Iterator[zmq.Context]:
    context = zmq.Context()
    yield context
    context.term()


def _socket(ctx: zmq.Context, kind: int) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    return sock


def _pair(ctx: zmq.Context, bind_kind: int, connect_kind: int) -> tuple[zmq.Socket, zmq.Socket]:
    bound = _socket(ctx, bind_kind)
    port = bound.bind_to_random_port("tcp://127.0.0.1")
    peer = _socket(ctx, connect_kind)
    peer.connect(f"tcp://127.0.0.1:{port}")
    return bound, peer


@pytest.fixture
def push_pull(ctx: zmq.Context) -> Iterator[tuple[zmq.Socket, zmq.Socket]]:
    pull, push = _pair(ctx, zmq.PULL, zmq.PUSH)
    yield push, pull
    push.close()
    pull.close()


@pytest.fixture
def pub_sub(ctx: zmq.Context) -> Iterator[tuple[zmq.Socket, zmq.Socket]]:
    """An agent-style publisher and a recorder-style subscriber, already subscribed."""
    pub, sub = _pair(ctx, zmq.XPUB, zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    # XPUB sees the subscription arrive, so nothing is lost to the slow-joiner race.
    assert pub.poll(TIMEOUT_MS), "subscription did not arrive"
    assert pub.recv() == b"\x01"
    yield pub, sub
    pub.close()
    sub.close()


@pytest.fixture
def req_rep(ctx: zmq.Context) -> Iterator[tuple[zmq.Socket, zmq.Socket]]:
    rep, req = _pair(ctx, zmq.REP, zmq.REQ)
    yield req, rep
    req.close()
    rep.close()


def _recv(sock: zmq.Socket) -> list[zmq.Frame]:
    assert sock.poll(TIMEOUT_MS), "nothing arrived in time"
    return sock.recv_multipart(copy=False, flags=zmq.NOBLOCK)


# ---------------------------------------------------------------------------------------------
# messages built by the tests


def _jpeg_like(n: int, seed: int) -> bytes:
    body = np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()
    return b"\xff\xd8\xff\xe0" + body + b"\xff\xd9"


def _frame(**overrides: object) -> FrameMessage:
    fields: dict[str, object] = dict(
        node_id="node-a",
        camera_serial=40123456,
        frame_index=17,
        seq=1234,
        capture_unix_ns=1_700_000_000_123_456_789,
        host_receive_unix_ns=1_700_000_000_125_000_000,
        ptp_offset_ns=-42,
        ptp_locked=True,
        encoding=Encoding.JPEG,
        width=64,
        height=48,
        left=_jpeg_like(300, 1),
        right=_jpeg_like(200, 2),
    )
    fields.update(overrides)
    return FrameMessage(**fields)  # type: ignore[arg-type]


def _camera(**overrides: object) -> CameraStatus:
    """A streaming camera's status; ``overrides`` change fields."""
    fields: dict[str, object] = dict(
        camera_serial=41000001,
        state="streaming",
        fps_measured=29.97,
        frames_captured=1800,
        frames_dropped=2,
        frames_published=1797,
        queue_depth=1,
        reopen_count=0,
        last_capture_unix_ns=1_700_000_000_990_000_000,
        error=None,
    )
    fields.update(overrides)
    return CameraStatus(**fields)  # type: ignore[arg-type]


def _status() -> AgentStatus:
    return AgentStatus(
        node_id="node-b",
        sent_unix_ns=1_700_000_001_000_000_000,
        status_seq=9,
        ptp=PtpState(state="locked", master_offset_ns=-17, gm_present=True),
        cameras=(
            _camera(),
            CameraStatus(
                camera_serial=41000002,
                state="reopening",
                fps_measured=0.0,
                frames_captured=10,
                frames_dropped=0,
                frames_published=10,
                queue_depth=0,
                reopen_count=3,
                last_capture_unix_ns=None,
                error="grab() timed out; reopening the camera",
            ),
        ),
        software_version="0.1.0",
    )


def _header(msg: FrameMessage) -> bytearray:
    return bytearray(msg.to_parts()[0])


def _decode_error(parts: list, match: str, kind: type[Exception] = MalformedMessageError) -> str:
    with pytest.raises(kind, match=match) as info:
        FrameMessage.from_parts(parts)
    return str(info.value)


# ---------------------------------------------------------------------------------------------
# frames


def test_errors_are_user_errors_and_value_errors():
    assert issubclass(MalformedMessageError, UserError)
    assert issubclass(MalformedMessageError, ValueError)
    assert issubclass(UnknownVersionError, MalformedMessageError)


def test_header_follows_the_documented_layout():
    msg = _frame()
    header = bytes(msg.to_parts()[0])
    assert header == msg.header()
    assert len(header) == DOC_HEADER.size == 112
    fields = DOC_HEADER.unpack(header)
    node = b"node-a"
    assert fields == (
        b"EGSF",
        1,
        112,
        1234,  # seq
        40123456,  # camera_serial
        17,  # frame_index
        1_700_000_000_123_456_789,
        1_700_000_000_125_000_000,
        -42,
        len(msg.left),
        len(msg.right),
        64,
        48,
        1,  # jpeg
        1,  # ptp locked
        len(node),
        0,
        node + b"\0" * (32 - len(node)),
    )


def test_jpeg_frame_round_trip_over_push_pull_without_copies(push_pull):
    push, pull = push_pull
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(2)]
    jpegs = [cv2.imencode(".jpg", im)[1].tobytes() for im in images]
    sent = _frame(encoding="jpeg", width=160, height=120, left=jpegs[0], right=jpegs[1])
    assert sent.encoding is Encoding.JPEG
    parts = sent.to_parts()
    assert parts[1] is jpegs[0] and parts[2] is jpegs[1]  # handed to zmq as given
    push.send_multipart(parts, copy=False)

    frames = _recv(pull)
    got = FrameMessage.from_parts(frames)
    assert got == sent
    for name in ("node_id", "camera_serial", "frame_index", "seq", "capture_unix_ns"):
        assert getattr(got, name) == getattr(sent, name)
    assert got.ptp_locked is True and got.ptp_offset_ns == -42
    for buf, frame in ((got.left, frames[1]), (got.right, frames[2])):
        assert isinstance(buf, memoryview) and buf.obj is frame  # a view of the zmq frame
    decoded = cv2.imdecode(np.frombuffer(got.left, np.uint8), cv2.IMREAD_COLOR)
    expected = cv2.imdecode(np.frombuffer(jpegs[0], np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(decoded, expected)


def test_raw_frame_round_trip_shares_memory_with_received_frames(push_pull):
    push, pull = push_pull
    height, width = 300, 400  # 360 kB per image: well above zmq's zero-copy threshold
    left = np.random.default_rng(5).integers(0, 256, (height, width, 3), dtype=np.uint8)
    right = np.ascontiguousarray(left[:, ::-1])
    sent = _frame(encoding=Encoding.RAW_BGR8, width=width, height=height, left=left, right=right)
    parts = sent.to_parts()
    assert np.shares_memory(np.frombuffer(parts[1], np.uint8), left)  # no copy on the way out
    push.send_multipart(parts, copy=False)

    frames = _recv(pull)
    got = FrameMessage.from_parts(frames)
    assert got.encoding is Encoding.RAW_BGR8 and (got.width, got.height) == (width, height)
    img = np.frombuffer(got.left, np.uint8).reshape(height, width, 3)
    np.testing.assert_array_equal(img, left)
    np.testing.assert_array_equal(np.frombuffer(got.right, np.uint8).reshape(img.shape), right)
    assert np.shares_memory(img, np.frombuffer(frames[1].buffer, np.uint8))
    assert np.shares_memory(
        np.frombuffer(got.right, np.uint8), np.frombuffer(frames[2].buffer, np.uint8)
    )


def test_decode_accepts_copied_bytes_parts(push_pull):
    push, pull = push_pull
    sent = _frame(ptp_locked=False, ptp_offset_ns=1_500_000)
    push.send_multipart(sent.to_parts())
    assert pull.poll(TIMEOUT_MS)
    parts = pull.recv_multipart()
    assert all(isinstance(p, bytes) for p in parts)
    got = FrameMessage.from_parts(parts)
    assert got == sent and got.ptp_locked is False and got.ptp_offset_ns == 1_500_000


def test_wrong_magic_is_not_an_egosurg_message():
    parts = _frame().to_parts()
    header = _header(_frame())
    header[0:4] = b"XXXX"
    msg = _decode_error([bytes(header), *parts[1:]], "magic")
    assert "b'XXXX'" in msg and "not an EgoSurg message" in msg


def test_status_magic_given_to_the_frame_decoder_names_decode_published():
    msg = _decode_error(_status().to_parts(), "agent status")
    assert "decode_published" in msg


@pytest.mark.parametrize("count", [0, 1, 2, 4])
def test_wrong_part_count(count):
    parts = _frame().to_parts()
    parts = [*parts, b"extra"][:count]
    msg = _decode_error(parts, f"has {count} parts")
    assert "expected 3" in msg


def test_truncated_header():
    parts = _frame().to_parts()
    msg = _decode_error([bytes(parts[0])[:50], *parts[1:]], "50 bytes")
    assert "112" in msg
    _decode_error([bytes(parts[0])[:3], *parts[1:]], "too short")


def test_header_size_field_must_match():
    parts = _frame().to_parts()
    header = _header(_frame())
    struct.pack_into("<H", header, OFF_HEADER_BYTES, 120)
    _decode_error([bytes(header), *parts[1:]], "120 bytes")


@pytest.mark.parametrize("version", [0, 2, 7])
def test_unknown_version(version):
    parts = _frame().to_parts()
    header = _header(_frame())
    struct.pack_into("<H", header, OFF_VERSION, version)
    msg = _decode_error(
        [bytes(header), *parts[1:]], f"wire version {version} ", UnknownVersionError
    )
    assert "supports 1" in msg and "upgrade" in msg
    # The version decides before anything else: a future version may have other parts.
    with pytest.raises(UnknownVersionError):
        FrameMessage.from_parts([bytes(header)])


def test_header_lengths_must_match_the_buffers():
    parts = _frame().to_parts()
    msg = _decode_error([parts[0], parts[1], bytes(parts[2])[:-1]], "right image")
    assert f"{len(parts[2])} bytes" in msg and f"{len(parts[2]) - 1} bytes" in msg


def test_oversized_image_is_rejected_on_decode_and_on_construction():
    parts = _frame().to_parts()
    header = _header(_frame())
    struct.pack_into("<Q", header, OFF_LEFT_BYTES, MAX_FRAME_BYTES + 1)
    _decode_error([bytes(header), *parts[1:]], "MAX_FRAME_BYTES")
    huge = b"\xff\xd8" + bytes(MAX_FRAME_BYTES)
    with pytest.raises(MalformedMessageError, match="MAX_FRAME_BYTES"):
        _frame(left=huge)


def test_raw_size_must_be_width_height_3():
    with pytest.raises(MalformedMessageError, match=r"raw_bgr8 at 4x2 needs width\*height\*3 = 24"):
        _frame(encoding=Encoding.RAW_BGR8, width=4, height=2, left=bytes(24), right=bytes(23))
    good = _frame(encoding=Encoding.RAW_BGR8, width=4, height=2, left=bytes(24), right=bytes(24))
    header = _header(good)
    struct.pack_into("<H", header, OFF_WIDTH, 5)  # the header now claims 5x2
    _decode_error([bytes(header), *good.to_parts()[1:]], "raw_bgr8 at 5x2")


def test_jpeg_must_start_with_soi():
    with pytest.raises(MalformedMessageError, match="starts with 89 50, not FF D8"):
        _frame(right=b"\x89PNG\r\n")
    with pytest.raises(MalformedMessageError, match="not a JPEG"):
        _frame(left=b"")
    # The same bytes with the header saying raw: a jpeg claim is checked on decode too.
    raw = _frame(encoding=Encoding.RAW_BGR8, width=2, height=1, left=bytes(6), right=bytes(6))
    header = _header(raw)
    header[OFF_ENCODING] = 1
    _decode_error([bytes(header), *raw.to_parts()[1:]], "not a JPEG")
    header[OFF_ENCODING] = 9
    _decode_error([bytes(header), *raw.to_parts()[1:]], "encoding code 9")


@pytest.mark.parametrize(("width", "height"), [(0, 10), (10, 0), (8193, 10), (10, 9000)])
def test_image_size_limits(width, height):
    with pytest.raises(MalformedMessageError, match=r"outside 1\.\.8192"):
        _frame(width=width, height=height)


def test_node_id_must_be_short_utf8():
    parts = _frame().to_parts()
    header = _header(_frame())
    header[OFF_NODE_LEN] = 2
    header[OFF_NODE : OFF_NODE + 32] = b"\xff\xfe" + bytes(30)
    _decode_error([bytes(header), *parts[1:]], "not valid UTF-8")
    with pytest.raises(MalformedMessageError, match=r"1\.\.32 UTF-8 bytes"):
        _frame(node_id="n" * 33)
    with pytest.raises(MalformedMessageError, match=r"1\.\.32 UTF-8 bytes"):
        _frame(node_id="")
    with pytest.raises(MalformedMessageError, match="UTF-8"):
        _frame(node_id="bad\udcff")
    assert FrameMessage.from_parts(_frame(node_id="nœud-é").to_parts()).node_id == "nœud-é"


@pytest.mark.parametrize("name", ["frame_index", "seq", "camera_serial"])
def test_negative_indices_are_rejected(name):
    with pytest.raises(MalformedMessageError, match=f"{name}=-1 must not be negative"):
        _frame(**{name: -1})


def test_out_of_range_index_on_the_wire_is_rejected():
    parts = _frame().to_parts()
    header = _header(_frame())
    struct.pack_into("<Q", header, OFF_FRAME_INDEX, 2**64 - 1)
    _decode_error([bytes(header), *parts[1:]], "frame_index")


def test_field_types_are_checked_on_construction():
    with pytest.raises(MalformedMessageError, match="ptp_locked"):
        _frame(ptp_locked=1)
    with pytest.raises(MalformedMessageError, match="must be an integer"):
        _frame(seq=1.5)
    with pytest.raises(MalformedMessageError, match="encoding 'png' is unknown"):
        _frame(encoding="png")
    with pytest.raises(MalformedMessageError, match="expected bytes or a buffer"):
        _frame(left="not bytes")


def test_garbage_never_escapes_as_another_exception():
    """Whatever arrives, a receiver sees MalformedMessageError or a message, never a crash."""
    rng = random.Random(7)
    good = [bytes(p) for p in _frame().to_parts()]
    good_status = _status().to_parts()[0]
    for _ in range(500):
        parts = [bytearray(p) for p in rng.choice([good, [good_status]])]
        for _ in range(rng.randint(1, 4)):
            part = rng.choice(parts)
            if part and rng.random() < 0.7:
                part[rng.randrange(len(part))] = rng.randrange(256)
            else:
                del part[rng.randrange(len(part) + 1) :]
        try:
            decode_published([bytes(p) for p in parts])
        except MalformedMessageError:
            pass


# ---------------------------------------------------------------------------------------------
# agent status and dispatch


def test_status_and_frames_share_a_pub_socket_and_dispatch(pub_sub):
    pub, sub = pub_sub
    status = _status()
    frame = _frame(seq=5)
    pub.send_multipart(status.to_parts(), copy=False)
    pub.send_multipart(frame.to_parts(), copy=False)

    got_status = decode_published(_recv(sub))
    got_frame = decode_published(_recv(sub))
    assert isinstance(got_status, AgentStatus) and got_status == status
    assert got_status.cameras[1].error == "grab() timed out; reopening the camera"
    assert got_status.cameras[0].fps_measured == 29.97
    assert isinstance(got_frame, FrameMessage) and got_frame == frame and got_frame.seq == 5


def test_decode_published_rejects_unknown_magic():
    with pytest.raises(MalformedMessageError, match=r"b'RIFF' is not an EgoSurg message"):
        decode_published([b"RIFF\x01\x00{}"])
    with pytest.raises(MalformedMessageError, match="0 parts"):
        decode_published([])
    with pytest.raises(MalformedMessageError, match="too short"):
        decode_published([b"EG"])


def _status_with_body(body: bytes, version: int = 1) -> list[bytes]:
    return [b"EGSH" + struct.pack("<H", version) + body]


def _status_json() -> dict:
    part = _status().to_parts()[0]
    assert part[:6] == b"EGSH\x01\x00"
    return json.loads(part[6:].decode("utf-8"))


def test_status_ignores_unknown_fields():
    body = _status_json()
    body["disk_free_bytes"] = 123
    body["cameras"][0]["temperature_c"] = 41.5
    assert AgentStatus.from_parts(_status_with_body(json.dumps(body).encode())) == _status()


@pytest.mark.parametrize(
    ("path", "match"),
    [
        (("cameras",), "missing field 'cameras'"),
        (("ptp", "gm_present"), "agent status ptp: missing field 'gm_present'"),
        (("cameras", 1, "reopen_count"), r"cameras\[1\]: missing field 'reopen_count'"),
    ],
)
def test_status_missing_field(path, match):
    body = _status_json()
    target = body
    for key in path[:-1]:
        target = target[key]
    del target[path[-1]]
    with pytest.raises(MalformedMessageError, match=match):
        AgentStatus.from_parts(_status_with_body(json.dumps(body).encode()))


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda b: b.update(status_seq="9"), "'status_seq'='9' must be an integer"),
        (lambda b: b.update(status_seq=True), "must be an integer"),
        (lambda b: b["cameras"][0].update(state="melting"), "'melting' is unknown"),
        (lambda b: b["ptp"].update(state="maybe"), "ptp state 'maybe' is unknown"),
        (lambda b: b["cameras"][0].update(frames_dropped=-1), "must not be negative"),
        (lambda b: b.update(cameras={}), "must be a list"),
    ],
)
def test_status_field_types_and_values(change, match):
    body = _status_json()
    change(body)
    with pytest.raises(MalformedMessageError, match=match):
        AgentStatus.from_parts(_status_with_body(json.dumps(body).encode()))


def test_status_bad_bodies_and_versions():
    with pytest.raises(MalformedMessageError, match="not valid JSON"):
        AgentStatus.from_parts(_status_with_body(b'{"node_id": '))
    with pytest.raises(MalformedMessageError, match="not UTF-8"):
        AgentStatus.from_parts(_status_with_body(b'{"node_id": "\xff"}'))
    with pytest.raises(MalformedMessageError, match="JSON list, expected a JSON object"):
        AgentStatus.from_parts(_status_with_body(b"[1, 2]"))
    with pytest.raises(MalformedMessageError, match="not valid JSON"):
        AgentStatus.from_parts(_status_with_body(b'{"fps": NaN}'))
    with pytest.raises(UnknownVersionError, match=r"wire version 3 .*supports 1"):
        AgentStatus.from_parts(_status_with_body(b"{}", version=3))
    with pytest.raises(MalformedMessageError, match="has 2 parts, expected 1"):
        AgentStatus.from_parts([*_status().to_parts(), b""])


def test_status_construction_is_validated():
    with pytest.raises(MalformedMessageError, match="fps_measured"):
        _camera(fps_measured=float("nan"))
    with pytest.raises(MalformedMessageError, match="'synced' is unknown"):
        PtpState(state="synced")
    status = _status()
    as_list = AgentStatus(
        node_id=status.node_id,
        sent_unix_ns=status.sent_unix_ns,
        status_seq=status.status_seq,
        ptp=status.ptp,
        cameras=list(status.cameras),  # type: ignore[arg-type]
        software_version=status.software_version,
    )
    assert as_list == status and isinstance(as_list.cameras, tuple)


# ---------------------------------------------------------------------------------------------
# control


def test_control_round_trip_over_req_rep(req_rep):
    req, rep = req_rep
    request = ControlRequest(
        verb="start", args={"session": "case-0042", "case": {"room": "OR 3", "ü": [1, 2.5]}}
    )
    req.send(request.to_bytes())
    [frame] = _recv(rep)
    got = ControlRequest.from_bytes(frame)
    assert got == request and got.request_id == request.request_id

    reply = ControlReply(
        ok=False,
        error="PTP is unlocked on node-b; wait for ptp4l to lock, then start again",
        request_id=got.request_id,
    )
    rep.send(reply.to_bytes())
    [answer] = _recv(req)
    back = ControlReply.from_bytes(answer.bytes)
    assert back == reply and back.result == {} and back.ok is False


def test_control_requests_get_distinct_ids_and_all_verbs_round_trip():
    ids = set()
    for verb in CONTROL_VERBS:
        request = ControlRequest(verb=verb)
        assert ControlRequest.from_bytes(request.to_bytes()) == request
        ids.add(request.request_id)
    assert len(ids) == len(CONTROL_VERBS)
    ok = ControlReply(ok=True, result={"recording": True}, request_id="r1")
    assert ControlReply.from_bytes(ok.to_bytes()) == ok


def test_unknown_verb_lists_the_valid_ones():
    with pytest.raises(MalformedMessageError, match="'launch' is unknown") as info:
        ControlRequest(verb="launch")
    assert all(v in str(info.value) for v in CONTROL_VERBS)
    wire = json.dumps(
        {"egosurg": "control", "version": 1, "verb": "launch", "args": {}, "request_id": "x"}
    )
    with pytest.raises(MalformedMessageError, match="valid verbs: start, stop, status, heartbeat"):
        ControlRequest.from_bytes(wire.encode())


def test_control_envelope_is_checked():
    request = json.loads(ControlRequest(verb="stop", request_id="abc").to_bytes())
    assert request["egosurg"] == "control" and request["version"] == 1

    def wire(**changes: object) -> bytes:
        return json.dumps({**request, **changes}).encode()

    with pytest.raises(UnknownVersionError, match=r"version 2 is not supported .*supports 1"):
        ControlRequest.from_bytes(wire(version=2))
    with pytest.raises(MalformedMessageError, match="'reply' message, expected 'control'"):
        ControlRequest.from_bytes(wire(egosurg="reply"))
    with pytest.raises(MalformedMessageError, match="not an EgoSurg control message"):
        ControlRequest.from_bytes(json.dumps({"verb": "stop"}).encode())
    with pytest.raises(MalformedMessageError, match="not valid JSON"):
        ControlRequest.from_bytes(b"stop please")
    with pytest.raises(MalformedMessageError, match="JSON str, expected a JSON object"):
        ControlReply.from_bytes(b'"ok"')
    for missing in ("args", "request_id", "verb"):
        incomplete = {k: v for k, v in request.items() if k != missing}
        with pytest.raises(MalformedMessageError, match=f"missing field '{missing}'"):
            ControlRequest.from_bytes(json.dumps(incomplete).encode())
    with pytest.raises(MalformedMessageError, match=r"'args'=.* must be an object"):
        ControlRequest.from_bytes(wire(args=[1]))


def test_control_reply_rules():
    with pytest.raises(MalformedMessageError, match="non-empty message"):
        ControlReply(ok=False, request_id="r")
    with pytest.raises(MalformedMessageError, match="error must be null"):
        ControlReply(ok=True, error="oops", request_id="r")
    with pytest.raises(MalformedMessageError, match="cannot be sent as JSON"):
        ControlReply(ok=True, result={"when": object()}, request_id="r")


def test_numpy_scalars_become_plain_values():
    """Agents often count with numpy; the records hold plain ints so JSON and struct accept them."""
    msg = _frame(frame_index=np.int64(3), seq=np.uint64(8), ptp_locked=np.bool_(False))
    assert type(msg.frame_index) is int and type(msg.seq) is int and msg.ptp_locked is False
    assert FrameMessage.from_parts(msg.to_parts()) == msg
    counters: dict[str, Any] = dict(
        camera_serial=np.uint32(5), fps_measured=np.float32(12.5), frames_captured=np.int64(3)
    )
    cam = CameraStatus(
        **counters,
        state="stalled",
        frames_dropped=0,
        frames_published=3,
        queue_depth=0,
        reopen_count=0,
    )
    assert type(cam.camera_serial) is int and cam.fps_measured == 12.5
    sent: Any = np.int64(7)
    status = AgentStatus(
        node_id="node-c",
        sent_unix_ns=sent,
        status_seq=0,
        ptp=PtpState(state="no_pmc"),
        cameras=(cam,),
        software_version="0.1.0",
    )
    assert AgentStatus.from_parts(status.to_parts()) == status
