"""A capture agent written only from the documented contract, for cameras EgoSurg does not know.

Sources: docs/capture.md ("Writing an agent: the contract") and the byte layout in
protocol/wire/__init__.py's docstring. It imports nothing of EgoSurg (no protocol/, no
capture_agent/):
frames are packed with ``struct`` from the documented header table and every JSON body is written
by hand, so a recorder that records from it shows that the documents suffice.

What it does, as the contract asks:
- binds a PUB socket (frames + status) and a REP socket (control); with CURVE keys, both are
  CURVE servers admitting only the allow-listed client keys (pyzmq's ZAP authenticator);
- publishes synthetic stereo JPEG frames of each camera at ``fps`` (one ``seq`` for the agent,
  ``frame_index`` per camera) and a status message about once a second;
- answers every control request: ``status`` with ``cameras_info`` (+ ``status``), ``heartbeat``
  with its node id, ``start``/``stop`` and anything unreadable with ``ok: false``.

Tests change its answers through ``status_result`` (the ``result`` of an ok reply),
``status_refusal`` (answer ``ok: false`` with that error) or ``status_delay_s`` (answer late),
and read what it sent with ``frames_sent()``. ``publish_raw(parts)`` sends one message of any
parts on its frame socket (a fault: an oversize part).
"""

from __future__ import annotations

import json
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import zmq

# docs: "<4sHHQQQqqqQQHHBBBB32s", 112 bytes, little-endian, magic EGSF, version 1
HEADER = struct.Struct("<4sHHQQQqqqQQHHBBBB32s")
JPEG_CODE = 1
STATUS_PREFIX = b"EGSH" + struct.pack("<H", 1)


@dataclass
class SpecAgent:
    node_id: str
    serials: tuple[int, ...]
    frames_bind: str
    control_bind: str
    fps: float = 15.0
    width: int = 64
    height: int = 48
    resolution: str = "TEST64x48"  # not a ZED X mode: any name of letters, digits, _ . -
    # CURVE: (public, secret) of this agent and the client keys it admits; None = plaintext
    keypair: tuple[bytes, bytes] | None = None
    allowed_client_keys: tuple[bytes, ...] = ()
    status_result: Callable[[dict[str, Any]], dict[str, Any]] | None = None
    status_refusal: str | None = None
    status_delay_s: float = 0.0  # answer status this late (a recorder gives up after 1.5 s)
    sent: dict[int, list[tuple[int, int]]] = field(default_factory=dict)  # (index, capture ns)

    def __post_init__(self) -> None:
        self._ctx = zmq.Context()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._auth: Any = None  # pyzmq's ThreadAuthenticator, with CURVE
        self._images = {s: self._stereo_jpeg(s) for s in self.serials}
        self._raw: list[list[bytes]] = []  # messages for publish_raw, sent by the PUB thread

    # -- the camera: synthetic JPEGs, different per camera and side ----------------------------
    def _stereo_jpeg(self, serial: int) -> tuple[bytes, bytes]:
        out = []
        for side in range(2):
            img = np.full((self.height, self.width, 3), (serial * 37 + side * 90) % 256, np.uint8)
            cv2.putText(img, str(side), (4, self.height - 8), 0, 1.0, (255, 255, 255), 2)
            ok, buf = cv2.imencode(".jpg", img)
            assert ok
            out.append(buf.tobytes())
        return out[0], out[1]

    # -- life cycle ------------------------------------------------------------------------------
    def start(self) -> SpecAgent:
        pub = self._ctx.socket(zmq.PUB)
        rep = self._ctx.socket(zmq.REP)
        if self.keypair is not None:
            from zmq.auth.thread import ThreadAuthenticator

            self._auth = ThreadAuthenticator(self._ctx)
            self._auth.start()
            allowed = set(self.allowed_client_keys)
            self._auth.configure_curve_callback(domain="*", credentials_provider=_Allow(allowed))
            for sock in (pub, rep):
                sock.curve_publickey, sock.curve_secretkey = self.keypair
                sock.curve_server = True
        for sock in (pub, rep):
            sock.setsockopt(zmq.LINGER, 0)
        pub.bind(self.frames_bind)
        rep.bind(self.control_bind)
        self._threads = [
            threading.Thread(target=self._publish, args=(pub,), daemon=True),
            threading.Thread(target=self._control, args=(rep,), daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        if self._auth is not None:
            self._auth.stop()
        self._ctx.term()

    def __enter__(self) -> SpecAgent:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def publish_raw(self, parts: list[bytes]) -> None:
        """Send ``parts`` as one message on the frame socket, between two frames."""
        with self._lock:
            self._raw.append(parts)

    def frames_sent(self) -> dict[int, list[tuple[int, int]]]:
        with self._lock:
            return {s: list(v) for s, v in self.sent.items()}

    # -- PUB: frames and status ------------------------------------------------------------------
    def _publish(self, pub: zmq.Socket) -> None:
        period_ns = round(1e9 / self.fps)
        seq = status_seq = 0
        index = dict.fromkeys(self.serials, 0)
        next_frame = time.time_ns()
        next_status = 0.0
        try:
            while not self._stop.is_set():
                with self._lock:
                    raw, self._raw = self._raw, []
                for parts in raw:
                    pub.send_multipart(parts)
                if time.monotonic() >= next_status:
                    status_seq += 1
                    pub.send(STATUS_PREFIX + self._json(self._status_body(status_seq)))
                    next_status = time.monotonic() + 1.0
                now = time.time_ns()
                if now < next_frame:
                    time.sleep(min((next_frame - now) / 1e9, 0.02))
                    continue
                for k, serial in enumerate(self.serials):
                    capture = next_frame + k * 1_000_000  # cameras a millisecond apart
                    left, right = self._images[serial]
                    header = HEADER.pack(
                        b"EGSF", 1, HEADER.size, seq, serial, index[serial], capture,
                        time.time_ns(), 12, len(left), len(right), self.width, self.height,
                        JPEG_CODE, 1, len(self.node_id.encode()), 0, self.node_id.encode(),
                    )  # fmt: skip
                    pub.send_multipart([header, left, right])
                    with self._lock:
                        self.sent.setdefault(serial, []).append((index[serial], capture))
                    seq += 1
                    index[serial] += 1
                next_frame += period_ns
        finally:
            pub.close(linger=0)

    def _status_body(self, status_seq: int) -> dict[str, Any]:
        with self._lock:
            last = {s: (v[-1][1] if v else None) for s, v in self.sent.items()}
            count = {s: len(v) for s, v in self.sent.items()}
        return {
            "node_id": self.node_id,
            "sent_unix_ns": time.time_ns(),
            "status_seq": status_seq,
            "software_version": "spec-agent 1",
            "ptp": {"state": "locked", "master_offset_ns": 12, "gm_present": True},
            "cameras": [
                {
                    "camera_serial": s,
                    "state": "streaming" if count.get(s) else "closed",
                    "fps_measured": self.fps if count.get(s) else 0.0,
                    "frames_captured": count.get(s, 0),
                    "frames_dropped": 0,
                    "frames_published": count.get(s, 0),
                    "queue_depth": 0,
                    "reopen_count": 0,
                    "last_capture_unix_ns": last.get(s),
                    "error": None,
                }
                for s in self.serials
            ],
        }

    # -- REP: control ----------------------------------------------------------------------------
    def _control(self, rep: zmq.Socket) -> None:
        try:
            while not self._stop.is_set():
                if not rep.poll(50):
                    continue
                parts = rep.recv_multipart()
                rep.send(self._json(self._answer(parts)))
        finally:
            rep.close(linger=0)

    def _answer(self, parts: list[bytes]) -> dict[str, Any]:
        try:
            req = json.loads(parts[0].decode("utf-8"))
            ok_envelope = (
                len(parts) == 1 and isinstance(req, dict) and req.get("egosurg") == "control"
                and req.get("version") == 1 and isinstance(req.get("request_id"), str)
                and req["request_id"]
            )  # fmt: skip
        except (UnicodeDecodeError, ValueError):
            req, ok_envelope = None, False
        if not ok_envelope:
            return self._reply("", error="not an EgoSurg control request (version 1)")
        rid, verb = req["request_id"], req.get("verb")
        if verb == "heartbeat":
            return self._reply(rid, result={"node_id": self.node_id})
        if verb == "status":
            self._stop.wait(self.status_delay_s)
            if self.status_refusal is not None:
                return self._reply(rid, error=self.status_refusal)
            result = {"cameras_info": self._cameras_info(), "status": self._status_body(0)}
            if self.status_result is not None:
                result = self.status_result(result)
            return self._reply(rid, result=result)
        if verb in ("start", "stop"):
            return self._reply(rid, error="an agent does not record; send it to the recorder")
        return self._reply(rid, error=f"unknown verb {str(verb)[:40]!r}")

    def _cameras_info(self) -> list[dict[str, Any]]:
        return [
            {
                "camera_serial": s,
                "resolution": self.resolution,
                "width": self.width,
                "height": self.height,
                "fps": self.fps,
                "encoding": "jpeg",
                "factory_conf": None,  # a camera without a factory calibration file
            }
            for s in self.serials
        ]

    @staticmethod
    def _reply(rid: str, *, result: dict | None = None, error: str | None = None) -> dict:
        return {
            "egosurg": "reply",
            "version": 1,
            "ok": error is None,
            "result": result or {},
            "error": error,
            "request_id": rid,
        }

    @staticmethod
    def _json(obj: dict[str, Any]) -> bytes:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode("utf-8")


class _Allow:
    """pyzmq's credentials provider: admit exactly these client public keys."""

    def __init__(self, keys: set[bytes]) -> None:
        self.keys = keys

    def callback(self, domain: str, key: bytes) -> bool:
        return key in self.keys
