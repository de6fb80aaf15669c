"""A client for the recorder's control socket, shared by ``egosurg record``/``status`` and the
operator console's ``rig`` object.

Example::

    from capture_agent.rig_client import RigClient
    rig = RigClient.connect()                    # EGOSURG_RECORDER or tcp://127.0.0.1:5560
    rig.start("case-0042", surgeon="A. Smith")
    rig.status()["cameras"]
    img = rig.last_frame(41234567)               # BGR image from the agent's live stream
    rig.stop()
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np
import zmq

from capture_agent.config import RigConfig, connect_address
from protocol.errors import UserError
from protocol.images import decode_image
from protocol.messages import (
    ControlReply,
    ControlRequest,
    FrameMessage,
    MalformedMessageError,
    decode_published,
)

DEFAULT_RECORDER = "tcp://127.0.0.1:5560"


class RecorderUnreachableError(UserError, ConnectionError):
    pass


class CommandRefusedError(UserError, RuntimeError):
    """The recorder answered, and said no; the message is its reason."""


def resolve_recorder(url: str | None = None, config: str | None = None) -> str:
    if url:
        return url
    if config:
        return connect_address(RigConfig.from_toml(config).control_bind)
    return os.environ.get("EGOSURG_RECORDER", DEFAULT_RECORDER)


class RigClient:
    def __init__(self, recorder_url: str, timeout_s: float = 5.0) -> None:
        self.recorder_url = recorder_url
        self.timeout_s = timeout_s
        self._ctx: zmq.Context = zmq.Context.instance()

    @classmethod
    def connect(cls, url: str | None = None, config: str | None = None) -> RigClient:
        return cls(resolve_recorder(url, config))

    def request(self, verb: str, **args: Any) -> dict[str, Any]:
        """One request/reply; a fresh REQ socket each time, so a lost reply never wedges us."""
        sock = self._ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        ms = int(self.timeout_s * 1000)
        sock.setsockopt(zmq.RCVTIMEO, ms)
        sock.setsockopt(zmq.SNDTIMEO, ms)
        try:
            sock.connect(self.recorder_url)
            req = ControlRequest(verb=verb, args=args)
            sock.send(req.to_bytes())
            try:
                raw = sock.recv()
            except zmq.Again:
                raise RecorderUnreachableError(
                    f"no recorder answered at {self.recorder_url} within {self.timeout_s:g} s; "
                    "is 'egosurg recorder' running (systemctl status egosurg-recorder)? Use "
                    "--recorder or EGOSURG_RECORDER to point elsewhere"
                ) from None
            try:
                reply = ControlReply.from_bytes(raw)
            except MalformedMessageError as exc:
                raise RecorderUnreachableError(
                    f"{self.recorder_url} answered with something that is not an EgoSurg "
                    f"reply ({exc}); is that address really the recorder?"
                ) from None
        finally:
            sock.close(linger=0)
        if not reply.ok:
            raise CommandRefusedError(reply.error or f"{verb} refused")
        return reply.result

    # -- the operator's verbs -----------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        return self.request("status")

    def start(self, case: str, planned_duration_min: float | None = None, **meta: str) -> dict:
        args: dict[str, Any] = {"case": case, "meta": {k: str(v) for k, v in meta.items()}}
        if planned_duration_min is not None:
            args["planned_duration_min"] = float(planned_duration_min)
        return self.request("start", **args)

    def stop(self) -> dict[str, Any]:
        return self.request("stop")

    def last_frame(self, camera: int, side: str = "left", timeout_s: float = 3.0) -> np.ndarray:
        """The next frame of ``camera`` from its agent's live stream, as a BGR image."""
        if side not in ("left", "right"):
            raise ValueError("side must be 'left' or 'right'")
        status = self.status()
        cams = {c["serial"]: c for c in status["cameras"]}
        if camera not in cams or cams[camera]["node_id"] is None:
            known = ", ".join(str(s) for s in cams) or "none"
            raise CommandRefusedError(f"camera {camera} is not streaming; cameras: {known}")
        node = cams[camera]["node_id"]
        endpoint = next(a["frames"] for a in status["agents"] if a["node_id"] == node)
        sub = self._ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.RCVHWM, 10)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(endpoint)
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline:
                if not sub.poll(100):
                    continue
                msg = decode_published(sub.recv_multipart(copy=False))
                if isinstance(msg, FrameMessage) and msg.camera_serial == camera:
                    buf = msg.left if side == "left" else msg.right
                    return decode_image(bytes(buf), msg.encoding.value, msg.width, msg.height)
        finally:
            sub.close(linger=0)
        raise CommandRefusedError(f"no frame from camera {camera} within {timeout_s:g} s")
