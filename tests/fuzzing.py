"""Fuzzing targets shared by ``tests/capture_agent/test_fuzz.py`` (hypothesis, a bounded sample) and
``bench/bench_fuzz.py`` (100k+ cases from a seeded mutator).

Every mutator takes a ``Chooser``: ``RandomChooser`` (a seeded ``random.Random``, fast) or
``DataChooser`` (hypothesis' ``data.draw``, which shrinks a failure to a small example). The
properties:

- decoders (``decode_published``, ``AgentStatus``, ``ControlRequest``/``ControlReply``) accept
  or raise ``MalformedMessageError``, nothing else, within ``DECODE_LIMIT_S``;
- a daemon's control socket (``ControlProbe``, a real DEALER on loopback) gives exactly one
  decodable reply per request, then answers a valid ``status``;
- the session reader (``ReaderWorker``, a child process, killed on a hang) opens a damaged file
  and reads everything in it, or raises ``SessionFormatError``, within ``READ_LIMIT_S``.

``python -m tests.fuzzing reader-worker`` is the reader's child process: one path per stdin
line, one JSON outcome per stdout line.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import select
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

REPO = Path(__file__).resolve().parents[1]
DECODE_LIMIT_S = 2.0  # one decode of a message under 1 MiB; more is a hang
READ_LIMIT_S = 20.0  # one damaged small session opened and read in full; more is a hang
REPLY_LIMIT_S = 5.0  # one control reply from an idle daemon

JPEG = b"\xff\xd8" + bytes(range(256)) + b"\xff\xd9"


class Hang(Exception):
    """A target that did not return within its limit."""


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raise ``Hang`` in the main thread after ``seconds`` (SIGALRM; Python code only)."""

    def on_alarm(_sig: int, _frame: object) -> None:
        raise Hang(f"no answer in {seconds:g} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


# --------------------------------------------------------------------------------------------
# Choosers
# --------------------------------------------------------------------------------------------


class Chooser(Protocol):
    def int(self, lo: int, hi: int) -> int: ...
    def bytes(self, n: int) -> bytes: ...


class RandomChooser:
    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)

    def int(self, lo: int, hi: int) -> int:
        return self.rng.randint(lo, hi)

    def bytes(self, n: int) -> bytes:
        return self.rng.randbytes(n)


class DataChooser:
    """Draws through hypothesis, so failing cases shrink."""

    def __init__(self, data: Any) -> None:
        from hypothesis import strategies as st

        self.data, self.st = data, st

    def int(self, lo: int, hi: int) -> int:
        return self.data.draw(self.st.integers(lo, hi))

    def bytes(self, n: int) -> bytes:
        return self.data.draw(self.st.binary(min_size=n, max_size=n))


def pick(c: Chooser, options: list | tuple) -> Any:
    return options[c.int(0, len(options) - 1)]


# --------------------------------------------------------------------------------------------
# Valid messages to start from
# --------------------------------------------------------------------------------------------


def valid_frame_parts(c: Chooser) -> list[bytes]:
    from protocol.wire import FrameMessage

    raw = c.int(0, 1) == 1
    width, height = c.int(1, 16), c.int(1, 16)
    image = bytes(width * height * 3) if raw else JPEG + c.bytes(c.int(0, 40))
    msg = FrameMessage(
        node_id=pick(c, ("n0", "orin-a", "ü" * 16)),
        camera_serial=c.int(0, 2**63 - 1),
        frame_index=c.int(0, 2**40),
        seq=c.int(0, 2**40),
        capture_unix_ns=c.int(-(2**63), 2**63 - 1),
        host_receive_unix_ns=c.int(0, 2**62),
        ptp_offset_ns=c.int(-(10**9), 10**9),
        ptp_locked=c.int(0, 1) == 1,
        encoding="raw_bgr8" if raw else "jpeg",
        width=width,
        height=height,
        left=image,
        right=image,
    )
    return [bytes(p) for p in msg.to_parts()]


def valid_status_parts(c: Chooser) -> list[bytes]:
    from protocol.wire import AgentStatus, CameraStatus, PtpState

    cams = tuple(
        CameraStatus(
            camera_serial=c.int(0, 2**40),
            state=pick(c, ("streaming", "stalled", "reopening", "closed", "error")),
            fps_measured=c.int(0, 120) / 4,
            frames_captured=c.int(0, 10**6),
            frames_dropped=c.int(0, 10),
            frames_published=c.int(0, 10**6),
            queue_depth=c.int(0, 5),
            reopen_count=c.int(0, 3),
            last_capture_unix_ns=pick(c, (None, 1_700_000_000_000_000_000)),
            error=pick(c, (None, "camera vanished")),
        )
        for _ in range(c.int(0, 3))
    )
    st = AgentStatus(
        node_id="orin-a",
        sent_unix_ns=time.time_ns(),
        status_seq=c.int(0, 10**6),
        ptp=PtpState(state=pick(c, ("locked", "unlocked", "disabled")), master_offset_ns=-12),
        cameras=cams,
        software_version="0.1.0",
    )
    return st.to_parts()


def valid_request(c: Chooser, verbs: tuple[str, ...] = ("status", "heartbeat")) -> bytes:
    from protocol.wire import ControlRequest

    verb = pick(c, verbs)
    args: dict[str, Any] = {}
    if verb == "start":
        args = {"case": "case-1", "meta": {"room": "OR 3"}, "planned_duration_min": 1.0}
    return ControlRequest(verb=verb, args=args, request_id=uuid.uuid4().hex).to_bytes()


def valid_reply(c: Chooser) -> bytes:
    from protocol.wire import ControlReply

    ok = c.int(0, 1) == 1
    return ControlReply(
        ok=ok,
        result={"rig_name": "or3", "cameras": [1, 2]} if ok else {},
        error=None if ok else "PTP is unlocked on node-b",
        request_id=uuid.uuid4().hex,
    ).to_bytes()


# --------------------------------------------------------------------------------------------
# Mutators
# --------------------------------------------------------------------------------------------

# Offsets of the frame header's fields (protocol/wire/__init__.py's docstring): where a flip
# matters.
_HEADER_FIELDS = (0, 4, 6, 8, 16, 24, 32, 40, 48, 56, 64, 72, 74, 76, 77, 78, 79, 80, 111)


def mutate_bytes(c: Chooser, data: bytes) -> bytes:
    """One byte-level change: flips, a truncation, an extension, a random overwrite."""
    b = bytearray(data)
    op = c.int(0, 4)
    if op == 0 and b:  # flip a few bytes
        for _ in range(c.int(1, 4)):
            i = c.int(0, len(b) - 1)
            b[i] ^= c.int(1, 255)
    elif op == 1:  # truncate
        del b[c.int(0, len(b)) :]
    elif op == 2:  # extend
        b += c.bytes(c.int(1, 64))
    elif op == 3 and b:  # overwrite a run
        i = c.int(0, len(b) - 1)
        n = c.int(1, min(16, len(b) - i))
        b[i : i + n] = c.bytes(n)
    else:  # replace entirely
        b = bytearray(c.bytes(c.int(0, 200)))
    return bytes(b)


def mutate_header(c: Chooser, header: bytes) -> bytes:
    """A frame header with one field (or the byte at a field's start) set to an edge value."""
    b = bytearray(header)
    at = pick(c, _HEADER_FIELDS)
    width = pick(c, (1, 2, 8))
    value = pick(c, (0, 1, 2, 0xFF, 2**15, 2**31, 2**63, 2**64 - 1, c.int(0, 2**64 - 1)))
    raw = (value % (1 << (8 * width))).to_bytes(width, "little")
    b[at : at + width] = raw[: max(0, len(b) - at)]
    return bytes(b[: len(header)])


def mutate_parts(c: Chooser, parts: list[bytes], *, header_aware: bool = False) -> list[bytes]:
    """1..3 mutations of a multipart message: a part's bytes, its header field, the part count."""
    out = list(parts)
    for _ in range(c.int(1, 3)):
        op = c.int(0, 5)
        if op <= 1 and out:
            k = c.int(0, len(out) - 1)
            out[k] = mutate_bytes(c, out[k])
        elif op == 2 and out and header_aware:
            out[0] = mutate_header(c, out[0])
        elif op == 3 and out:
            del out[c.int(0, len(out) - 1)]
        elif op == 4:
            out.insert(c.int(0, len(out)), c.bytes(c.int(0, 32)))
        elif out:
            k = c.int(0, len(out) - 1)
            out[k] = mutate_json(c, out[k])
    return out


def random_json(c: Chooser, depth: int = 0) -> Any:
    kind = c.int(0, 9 if depth < 3 else 6)
    if kind == 0:
        return None
    if kind == 1:
        return c.int(0, 1) == 1
    if kind == 2:
        return pick(c, (0, -1, 2**63, -(2**63) - 1, 10**30, c.int(-(2**64), 2**64)))
    if kind == 3:
        return pick(c, (0.5, -0.0, 1e308, -1e-308, 30.0))
    if kind == 4:
        return pick(c, ("", "x", "\x1b[2J", "\u202e", "\ud800", "é" * 40, "\\" * 300, "null"))
    if kind == 5:
        return c.bytes(c.int(0, 12)).decode("latin-1")
    if kind == 6:
        return pick(c, ("status", "start", "stop", "heartbeat", "control", "reply"))
    if kind == 7:
        return [random_json(c, depth + 1) for _ in range(c.int(0, 3))]
    return {pick(c, ("a", "verb", "args", "case", "")): random_json(c, depth + 1)}


_RAW_JSON = (
    b"[" * 100_000,  # deep nesting: the parser's recursion
    b'{"egosurg": "control", "version": 1e400}',
    b'{"egosurg": "control", "version": NaN}',
    b'{"egosurg": "control", "version": 1, "verb": "status", "args": {}, "request_id": "\\ud800"}',
    b'{"egosurg": "control", "version": ' + b"9" * 5000 + b"}",
    b'{"egosurg": "control", "egosurg": "reply", "version": 1}',
)


def mutate_json(c: Chooser, data: bytes) -> bytes:
    """A JSON-level change to a JSON message (a key removed, retyped or added), or raw JSON
    edge cases; falls back to bytes when ``data`` is not JSON (binary messages)."""
    prefix, body = b"", data
    if data[:4] == b"EGSH":
        prefix, body = data[:6], data[6:]
    try:
        obj = json.loads(body)
    except (ValueError, RecursionError):
        return mutate_bytes(c, data)
    if c.int(0, 9) == 0:
        return prefix + pick(c, _RAW_JSON)
    target = obj
    path: list = []
    while isinstance(target, dict | list) and target and c.int(0, 2) > 0:
        key = pick(c, sorted(target)) if isinstance(target, dict) else c.int(0, len(target) - 1)
        path.append(key)
        target = target[key]
    op = c.int(0, 3)
    if not path:
        obj = random_json(c) if op == 0 else obj
        if isinstance(obj, dict) and op > 0:
            obj[pick(c, ("extra", "egosurg", "version", "verb", "request_id"))] = random_json(c)
    else:
        parent = obj
        for key in path[:-1]:
            parent = parent[key]
        last = path[-1]
        if op == 0 and isinstance(parent, dict):
            del parent[last]
        else:
            parent[last] = random_json(c)
    text = json.dumps(obj, ensure_ascii=c.int(0, 1) == 1)
    return prefix + text.encode("utf-8", "surrogatepass")


def frame_case(c: Chooser) -> list[bytes]:
    """A mutated frame or status message, or random parts."""
    kind = c.int(0, 9)
    if kind <= 5:
        return mutate_parts(c, valid_frame_parts(c), header_aware=True)
    if kind <= 8:
        return mutate_parts(c, valid_status_parts(c))
    return [c.bytes(c.int(0, 120)) for _ in range(c.int(0, 4))]


def status_case(c: Chooser) -> bytes:
    """One mutated agent status part (JSON-level or byte-level)."""
    part = valid_status_parts(c)[0]
    return mutate_json(c, part) if c.int(0, 1) else mutate_bytes(c, part)


def reply_case(c: Chooser) -> bytes:
    reply = valid_reply(c)
    return mutate_json(c, reply) if c.int(0, 2) else mutate_bytes(c, reply)


def control_case(c: Chooser) -> list[bytes]:
    """1..3 parts for a control socket: mutated valid requests, replies, random bytes."""
    parts = []
    for _ in range(c.int(1, 3) if c.int(0, 3) == 0 else 1):
        kind = c.int(0, 5)
        if kind <= 2:
            parts.append(mutate_json(c, valid_request(c, ("status", "heartbeat", "start", "stop"))))
        elif kind == 3:
            parts.append(mutate_bytes(c, valid_request(c)))
        elif kind == 4:
            parts.append(mutate_json(c, valid_reply(c)))
        else:
            parts.append(c.bytes(c.int(0, 100)))
    return parts


# --------------------------------------------------------------------------------------------
# Decoder properties
# --------------------------------------------------------------------------------------------


def decode_frame_or_status(parts: list[bytes]) -> str:
    """'accepted' or 'rejected'; anything but ``MalformedMessageError`` propagates."""
    from protocol.wire import MalformedMessageError, decode_published

    try:
        with time_limit(DECODE_LIMIT_S):
            decode_published(parts)
    except MalformedMessageError:
        return "rejected"
    return "accepted"


def decode_control(data: bytes, kind: str) -> str:
    from protocol.wire import AgentStatus, ControlReply, ControlRequest, MalformedMessageError

    decode = {
        "request": ControlRequest.from_bytes,
        "reply": ControlReply.from_bytes,
        "status": lambda d: AgentStatus.from_parts([d]),
    }[kind]
    try:
        with time_limit(DECODE_LIMIT_S):
            msg = decode(data)
    except MalformedMessageError:
        return "rejected"
    # what a daemon accepted it can echo and forward: it re-encodes (a reply echoes the
    # request_id, the recorder's status carries the agents' status fields)
    again = msg.to_parts()[0] if kind == "status" else msg.to_bytes()
    if kind != "status":
        decode(again)
    return "accepted"


# --------------------------------------------------------------------------------------------
# A daemon's control socket
# --------------------------------------------------------------------------------------------


class ControlProbe:
    """A DEALER on a daemon's REP control socket: sends any parts, counts the replies.

    ``send(parts)`` sends one request and then a valid ``status``; it returns the reply to the
    request after checking that exactly one reply came before the status reply (REP answers in
    order) and that the daemon still answers ``status`` with ``ok``."""

    def __init__(self, endpoint: str, socket_setup: Any = None) -> None:
        import zmq

        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        if socket_setup is not None:
            socket_setup(self.sock)
        self.sock.connect(endpoint)

    def close(self) -> None:
        self.sock.close(linger=0)
        self.ctx.term()

    def _recv(self) -> bytes:
        if not self.sock.poll(int(REPLY_LIMIT_S * 1000)):
            raise Hang(f"no control reply in {REPLY_LIMIT_S:g} s")
        frames = self.sock.recv_multipart()
        if len(frames) != 2 or frames[0] != b"":
            raise AssertionError(f"a reply must be one part after the delimiter, got {frames!r}")
        return frames[1]

    def send(self, parts: list[bytes]) -> Any:
        from protocol.wire import ControlReply, ControlRequest

        status = ControlRequest(verb="status")
        self.sock.send_multipart([b"", *parts])
        self.sock.send_multipart([b"", status.to_bytes()])
        reply = ControlReply.from_bytes(self._recv())  # a valid reply, whatever was sent
        after = ControlReply.from_bytes(self._recv())
        if after.request_id != status.request_id:
            raise AssertionError(
                f"a second reply ({after!r}) came for one request, before the status reply"
            )
        if not after.ok:
            raise AssertionError(f"the daemon no longer answers status: {after.error}")
        if reply.request_id:  # a reply names the request it answers, or none
            try:
                sent = json.loads(parts[0]).get("request_id") if len(parts) == 1 else None
            except (ValueError, AttributeError):
                sent = None
            if reply.request_id != sent:
                raise AssertionError(f"reply request_id {reply.request_id!r} was not sent")
        return reply


# --------------------------------------------------------------------------------------------
# The session reader on damaged files
# --------------------------------------------------------------------------------------------


def write_small_session(path: Path) -> Path:
    """A real closed session: two cameras (one raw), sets with a missing member, two gaps."""
    from protocol.session import CameraInfo, GapKind, SessionWriter

    t0, period = 1_770_000_000_000_000_000, 33_333_333
    cams = [
        CameraInfo(camera_serial=101, node_id="n0", resolution="HD1200", width=1920,
                   height=1200, fps_nominal=30.0, encoding="jpeg",
                   factory_conf_text="[STEREO]\nBaseline=119.9\n"),
        CameraInfo(camera_serial=102, node_id="n1", resolution="TINY", width=4, height=2,
                   fps_nominal=30.0, encoding="raw_bgr8"),
    ]  # fmt: skip
    with SessionWriter(
        path,
        session_name="fuzz",
        case_metadata={"room": "OR 3"},
        cameras=cams,
        tolerance_ns=period // 2,
        rig_config_text='rig_name = "or3"\n',
        software_version="0.1.0",
        started_unix_ns=t0,
    ) as w:
        rows = {101: 0, 102: 0}
        for k in range(12):
            members = []
            for serial in (101, 102):
                if serial == 102 and k == 5:
                    members.append(-1)
                    continue
                if serial == 101:
                    left = JPEG + bytes([k]) * (200 + 37 * k) + b"\xff\xd9"
                    right = JPEG + bytes([k + 1]) * 150 + b"\xff\xd9"
                else:
                    left = right = bytes((k + i) % 256 for i in range(24))
                members.append(
                    w.append_frame(
                        serial,
                        left=left,
                        right=right,
                        capture_unix_ns=t0 + k * period + serial,
                        host_receive_unix_ns=t0 + k * period + 2_000_000,
                        recorder_receive_unix_ns=t0 + k * period + 3_000_000,
                        frame_index=k,
                        seq=2 * k + serial % 2,
                        ptp_offset_ns=-12,
                        ptp_locked=True,
                    )
                )
                rows[serial] += 1
            w.append_set(t0 + k * period, members, 1)
            if k % 4 == 3:
                w.flush()
        w.append_gap(
            102,
            kind=GapKind.FRAME_INDEX_GAP,
            first_missing_frame_index=5,
            missing_count=1,
            start_unix_ns=t0 + 4 * period,
            end_unix_ns=t0 + 6 * period,
        )
        w.append_gap(101, kind=GapKind.TIME_GAP, first_missing_frame_index=-1, missing_count=2,
                     start_unix_ns=t0 + 7 * period, end_unix_ns=t0 + 10 * period)  # fmt: skip
        w.close(t0 + 12 * period, {"rejected_messages": 0})
    return path


def live_ranges(data: bytes, join_bytes: int = 4096) -> list[tuple[int, int]]:
    """The ``[start, end)`` ranges of ``data`` that hold non-zero bytes: HDF5 preallocates, so
    most of a small session is zeros that no reader looks at; damage aims at what is read."""
    import numpy as np

    nz = np.flatnonzero(np.frombuffer(data, np.uint8))
    if not len(nz):
        return [(0, len(data))]
    breaks = np.flatnonzero(np.diff(nz) > join_bytes)
    starts = np.concatenate([[nz[0]], nz[breaks + 1]])
    ends = np.concatenate([nz[breaks], [nz[-1]]]) + 1
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def _offset(c: Chooser, n: int, live: list[tuple[int, int]]) -> int:
    if c.int(0, 3) == 0:
        return c.int(0, n - 1)
    start, end = pick(c, live)
    return c.int(start, end - 1)


def damage(c: Chooser, data: bytes, live: list[tuple[int, int]]) -> tuple[bytes, str]:
    """``data`` truncated, or with bytes flipped or zeroed at chosen offsets (mostly inside the
    ``live`` ranges); and a description of the damage."""
    n = len(data)
    op = c.int(0, 3)
    if op == 0:
        cut = _offset(c, n, live) if c.int(0, 1) else n - c.int(1, min(n, 1 << 20))
        return data[:cut], f"truncated to {cut} of {n} bytes"
    b = bytearray(data)
    if op == 1:
        at = [_offset(c, n, live) for _ in range(c.int(1, 8))]
        for i in at:
            b[i] ^= c.int(1, 255)
        return bytes(b), f"bytes flipped at {sorted(at)}"
    if op == 2:
        at = c.int(0, min(4096, n - 1))  # the superblock and the root group
        b[at] ^= c.int(1, 255)
        return bytes(b), f"metadata byte flipped at {at}"
    at, length = _offset(c, n, live), c.int(1, 4096)
    b[at : at + length] = bytes(len(b[at : at + length]))
    return bytes(b), f"{length} bytes zeroed at {at}"


def exercise_reader(path: str) -> dict[str, Any]:
    """Open ``path`` and read everything a tool reads; the outcome as a dict (in the worker)."""
    from protocol.session import SessionFormatError, SessionReader

    try:
        with SessionReader(path) as r:
            for serial in r.info.camera_serials:
                n = r.frame_count(serial)
                r.frame_table(serial)
                for row in {0, n - 1} if n else ():
                    r.frame_bytes(serial, row)
            r.sets()
            r.gaps()
            r.summary()
            problems = r.verify()
        return {"outcome": "accepted", "problems": len(problems)}
    except SessionFormatError as exc:
        return {"outcome": "rejected", "error": str(exc)[:300]}
    except Exception as exc:  # the property under test: nothing else may come out
        return {"outcome": "crash", "error": f"{type(exc).__name__}: {str(exc)[:300]}"}


class ReaderWorker:
    """A child process that runs ``exercise_reader`` per path; restarted after a hang."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None

    def _start(self) -> subprocess.Popen:
        env = dict(os.environ, PYTHONPATH=str(REPO))
        return subprocess.Popen(
            [sys.executable, "-m", "tests.fuzzing", "reader-worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            cwd=REPO,
            env=env,
            text=True,
            bufsize=1,
        )

    def read(self, path: Path, limit_s: float = READ_LIMIT_S) -> dict[str, Any]:
        """The outcome; ``{"outcome": "hang"}`` when no answer came within ``limit_s``."""
        if self.proc is None or self.proc.poll() is not None:
            self.proc = self._start()
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(f"{path}\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], limit_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            self.close()
            return {"outcome": "hang" if not ready else "crash", "error": "worker died or hung"}
        return json.loads(line)

    def close(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc = None


def _reader_worker() -> None:
    import logging

    logging.disable(logging.CRITICAL)  # the outcome is the answer; warnings are expected
    for line in sys.stdin:
        result = exercise_reader(line.rstrip("\n"))
        sys.stdout.write(json.dumps(result) + "\n")
        sys.stdout.flush()


if __name__ == "__main__" and sys.argv[1:] == ["reader-worker"]:
    _reader_worker()
