"""A client for the recorder's control socket, shared by ``egosurg record``/``status`` and the
operator console's ``rig`` object.

Example::

    from capture_agent.operator.rig_client import RigClient
    rig = RigClient.connect(config="/etc/egosurg/rig.toml")   # address and keys from rig.toml
    rig.start("case-0042", surgeon="A. Smith")
    rig.status()["cameras"]
    img = rig.last_frame(41234567)               # BGR image from the agent's live stream
    rig.stop()

Links are CURVE (``capture_agent/security.py``). The client's keypair and the recorder's public
key come from rig.toml's ``[security]`` (``operator_key``, ``public_key``) when ``--config`` is
given; ``EGOSURG_KEY`` (the operator's ``.key_secret``) and ``EGOSURG_RECORDER_KEY`` (the
recorder's ``.key``) override them or stand in for a config. Plaintext only where rig.toml says
``insecure = true``, or with ``EGOSURG_INSECURE=1`` for a rig that does.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import numpy as np
import zmq

from capture_agent.errors import CommandRefusedError, RecorderUnreachableError
from capture_agent.link_watch import DROPPED, HANDSHAKE_REFUSED, WatchedSub
from capture_agent.security import (
    CONTROL_MAX_BYTES,
    LinkSecurity,
    harden,
    load_keypair,
    load_public_key,
    make_client,
)
from protocol.errors import ConfigError
from protocol.formats.rig_config import RigConfig, connect_address
from protocol.images import decode_image
from protocol.wire import (
    ControlReply,
    ControlRequest,
    FrameMessage,
    MalformedMessageError,
    decode_published,
)
from protocol.wire.frame_limits import LARGEST_IMAGE_BYTES, frame_part_max_bytes

DEFAULT_RECORDER = "tcp://127.0.0.1:5560"
log = logging.getLogger(__name__)


def resolve_recorder(url: str | None = None, config: str | None = None) -> str:
    if url:
        return url
    if config:
        return connect_address(RigConfig.from_toml(config).control_bind)
    return os.environ.get("EGOSURG_RECORDER", DEFAULT_RECORDER)


def client_links(config: str | None = None) -> tuple[LinkSecurity, bytes | None]:
    """(this client's keys, the recorder's public key); see the module docstring."""
    env_key, env_server = os.environ.get("EGOSURG_KEY"), os.environ.get("EGOSURG_RECORDER_KEY")
    key_file = server_file = ""
    if config:
        sec = RigConfig.from_toml(config).security
        if sec.insecure:
            return LinkSecurity.plaintext(), None
        key_file, server_file = sec.operator_key, sec.public_key
    elif os.environ.get("EGOSURG_INSECURE") == "1" and not (env_key or env_server):
        log.warning("EGOSURG_INSECURE=1: talking to the recorder in plaintext")
        return LinkSecurity.plaintext(), None
    key_file, server_file = env_key or key_file, env_server or server_file
    if not key_file or not server_file:
        raise ConfigError(
            "no CURVE key to reach the recorder: pass --config rig.toml (its [security] names "
            "operator_key and the recorder's public_key), or set EGOSURG_KEY=<your .key_secret> "
            "and EGOSURG_RECORDER_KEY=<the recorder's .key>; make a key with 'egosurg keys "
            "generate --out ~/.egosurg --name operator' and add its .key to the rig's "
            "operator_keys. For a rig with insecure = true, set EGOSURG_INSECURE=1"
        )
    public, secret = load_keypair(key_file, "client secret key file")
    links = LinkSecurity(public_key=public, secret_key=secret, key_file=key_file)
    return links, load_public_key(server_file, "recorder public key file")


class RigClient:
    def __init__(
        self,
        recorder_url: str,
        timeout_s: float = 5.0,
        *,
        links: LinkSecurity | None = None,
        recorder_key: bytes | None = None,
        config: str | None = None,
    ) -> None:
        """``links``/``recorder_key`` default to ``client_links(config)``, read at the first
        request (so bad arguments are reported before a missing key)."""
        self.recorder_url = recorder_url
        self.timeout_s = timeout_s
        self._ctx: zmq.Context = zmq.Context.instance()
        self._links = links
        self._recorder_key = recorder_key
        self._config = config

    @classmethod
    def connect(cls, url: str | None = None, config: str | None = None) -> RigClient:
        return cls(resolve_recorder(url, config), config=config)

    @property
    def links(self) -> LinkSecurity:
        if self._links is None:
            self._links, self._recorder_key = client_links(self._config)
        return self._links

    def request(self, verb: str, **args: Any) -> dict[str, Any]:
        """One request/reply; a fresh REQ socket each time, so a lost reply never wedges us."""
        links = self.links
        sock = self._ctx.socket(zmq.REQ)
        harden(sock, CONTROL_MAX_BYTES)
        ms = int(self.timeout_s * 1000)
        sock.setsockopt(zmq.RCVTIMEO, ms)
        sock.setsockopt(zmq.SNDTIMEO, ms)
        try:
            make_client(sock, links, self._recorder_key)
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
                    + (
                        ""
                        if links.insecure
                        else ". If it runs, check that your key's .key is in the rig's "
                        "operator_keys and that the recorder key is that recorder's "
                        "(its log names refused keys)"
                    )
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
        """The recorder's view of the rig: every camera (streaming, fps, drops, PTP), every
        agent, the disk, and the recording if one runs (what 'egosurg status' shows)."""
        return self.request("status")

    def start(self, case: str, planned_duration_min: float | None = None, **meta: str) -> dict:
        """Start recording ``case`` (letters, digits, - _ .) with ``meta`` as the case's
        metadata; ``planned_duration_min`` is what the disk must hold (default: rig.toml's).
        Returns ``{"case", "file", "cameras", "started_unix_ns"}``; raises
        ``CommandRefusedError`` with the recorder's reason (a camera not streaming, PTP not
        locked, too little disk, already recording)."""
        args: dict[str, Any] = {"case": case, "meta": {k: str(v) for k, v in meta.items()}}
        if planned_duration_min is not None:
            args["planned_duration_min"] = float(planned_duration_min)
        return self.request("start", **args)

    def stop(self) -> dict[str, Any]:
        """Stop the recording; returns its summary (frames, drops, gaps per camera, the file).
        Raises ``CommandRefusedError`` when nothing is recording."""
        return self.request("stop")

    def last_frame(self, camera: int, side: str = "left", timeout_s: float = 3.0) -> np.ndarray:
        """The next frame of ``camera`` (its serial) from its agent's live stream, as a BGR
        image (height, width, 3); ``side`` is "left" or "right". Raises
        ``CommandRefusedError`` when the camera does not stream."""
        if side not in ("left", "right"):
            raise CommandRefusedError(f"side {side!r} is not a side; use 'left' or 'right'")
        status = self.status()
        cams = {c["serial"]: c for c in status["cameras"]}
        if camera not in cams or cams[camera]["node_id"] is None:
            known = ", ".join(str(s) for s in cams) or "none"
            raise CommandRefusedError(f"camera {camera} is not streaming; cameras: {known}")
        node = cams[camera]["node_id"]
        agent = next(a for a in status["agents"] if a["node_id"] == node)
        limit = int(status.get("max_image_bytes") or LARGEST_IMAGE_BYTES)
        server_key = agent.get("public_key", "").encode() or None

        def configure(sub: zmq.Socket) -> None:
            harden(sub, frame_part_max_bytes(limit))
            sub.setsockopt(zmq.RCVHWM, 10)
            sub.setsockopt(zmq.SUBSCRIBE, b"")
            # the agent's public key as the recorder (itself authenticated) has it in rig.toml
            make_client(sub, self.links, server_key)

        deadline = time.monotonic() + timeout_s
        # watched: a refused handshake or a dropped link is retried, and named if it persists
        link = WatchedSub(
            self._ctx,
            agent["frames"],
            configure,
            who="console",
            max_part_bytes=frame_part_max_bytes(limit),
        )
        failure = ""
        try:
            while time.monotonic() < deadline:
                for change in link.check():
                    failure = change.cause if change.kind in (DROPPED, HANDSHAKE_REFUSED) else ""
                if link.due():
                    link.recreate()
                if not link.sock.poll(100):
                    continue
                msg = decode_published(link.sock.recv_multipart(copy=False), max_image_bytes=limit)
                if (
                    isinstance(msg, FrameMessage)
                    and msg.camera_serial == camera
                    and msg.node_id == node
                ):
                    buf = msg.left if side == "left" else msg.right
                    return decode_image(bytes(buf), msg.encoding.value, msg.width, msg.height)
        finally:
            link.close()
        if failure:
            raise CommandRefusedError(
                f"no frame from camera {camera} within {timeout_s:g} s: the link to agent "
                f"{node} failed: {failure}"
            )
        raise CommandRefusedError(
            f"no frame from camera {camera} within {timeout_s:g} s; check it with "
            "'egosurg status' (is it streaming?)"
        )
