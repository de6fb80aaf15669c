"""The recorder's sockets (``capture_agent/recorder/recorder.py``): one SUB per agent, the
control REP, and one REQ per request to an agent, each CURVE unless rig.toml says
``insecure = true`` (``capture_agent/security.py``).

Each agent's SUB socket queues what ``receive_buffer_mb`` allows (split over the agents, counted
at the largest legal frame message; at most ``RECEIVE_QUEUE_S`` of that agent's frames: see
``receive_hwm``). ``AgentLinks`` owns them, the agents' public keys and the link guard (what the
authenticator refused, for ``status``).

Each SUB socket is watched (``capture_agent/link_watch.py``): a link that drops or whose
handshake is refused, by either side, is made again with backoff (0.2 s doubling to 5 s), so an
agent that sent an oversize part, or that refused the recorder's key until its config was fixed,
is heard again without restarting the recorder. ``check`` says what happened to the links,
``due`` which socket is to be made again (the I/O thread drains it first), ``recreate`` makes it.
"""

from __future__ import annotations

import functools
import math
import time
from pathlib import Path
from typing import Any

import zmq

from capture_agent.link_watch import LinkChange, WatchedSub
from capture_agent.security import (
    CONTROL_MAX_BYTES,
    LinkGuard,
    LinkSecurity,
    harden,
    load_public_key,
    make_client,
)
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.wire import ControlReply, ControlRequest, MalformedMessageError
from protocol.wire.agent_info import AgentReplyError
from protocol.wire.frame_limits import frame_message_max_bytes, frame_part_max_bytes

RECEIVE_QUEUE_S = 2.0  # the SUB socket's high-water mark, in seconds of one agent's frames


class AgentLinks:
    """The recorder's sockets and the keys they trust; used by the I/O thread only."""

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.ctx: zmq.Context = zmq.Context()  # its own: one ZAP authenticator per context
        self.guard: LinkGuard | None = None
        self.subs: dict[zmq.Socket, AgentEndpoint] = {}  # each agent's SUB socket of now
        self.watched: dict[str, WatchedSub] = {}  # node_id -> its SUB socket and link state
        self.generation = 0  # counts new sockets, so the I/O loop knows to poll them
        self.server_keys: dict[str, bytes] = {}  # agent endpoint -> the agent's public key

    def open(self) -> None:
        """One watched SUB socket per agent and the control REP."""
        config = self.config
        Path(config.output_dir).mkdir(parents=True, exist_ok=True)
        self.security: LinkSecurity = LinkSecurity.from_config(config.security)
        self.guard = LinkGuard(self.ctx, self.security, f"recorder {config.rig_name}")
        for a in config.agents:
            if not self.security.insecure:
                key = load_public_key(a.public_key, f"public key file of agent {a.node_id}")
                self.server_keys[a.frames] = self.server_keys[a.control] = key
            watched = WatchedSub(
                self.ctx,
                a.frames,
                functools.partial(self._configure_sub, a),
                who=f"recorder: agent {a.node_id}",
                max_part_bytes=frame_part_max_bytes(config.max_image_bytes),
            )
            self.watched[a.node_id] = watched
            self.subs[watched.sock] = a
        self.rep = self.ctx.socket(zmq.REP)
        harden(self.rep, CONTROL_MAX_BYTES)
        self.guard.make_server(self.rep, "recorder.control")
        self.rep.bind(config.control_bind)

    def _configure_sub(self, agent: AgentEndpoint, sub: zmq.Socket) -> None:
        """The options of ``agent``'s SUB socket, the first one and every one made again."""
        harden(sub, frame_part_max_bytes(self.config.max_image_bytes))
        sub.setsockopt(zmq.RCVHWM, receive_hwm(self.config, agent))
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        make_client(sub, self.security, self.server_keys.get(agent.frames))

    def check(self) -> list[tuple[AgentEndpoint, LinkChange]]:
        """What happened to the agents' links since the last call (never waits)."""
        now = time.monotonic()
        return [(self.subs[w.sock], c) for w in self.watched.values() for c in w.check(now)]

    def due(self) -> list[zmq.Socket]:
        """The SUB sockets whose link dropped or was refused and whose retry is due: drain
        each, then ``recreate`` it."""
        now = time.monotonic()
        return [w.sock for w in self.watched.values() if w.due(now)]

    def recreate(self, sub: zmq.Socket) -> tuple[AgentEndpoint, LinkChange]:
        """Close ``sub`` and make the agent's socket again (the same options and keys)."""
        agent = self.subs.pop(sub)
        watched = self.watched[agent.node_id]
        try:
            change = watched.recreate()
        finally:
            self.subs[watched.sock] = agent
        self.generation += 1
        return agent, change

    def link_counts(self, node_id: str) -> dict[str, Any]:
        """The state and counters of an agent's frame link, for ``status``."""
        watched = self.watched.get(node_id)
        return watched.counts.as_dict() if watched is not None else {}

    def close(self) -> None:
        for watched in self.watched.values():
            watched.close()
        self.rep.close(linger=0)
        if self.guard is not None:
            self.guard.close()

    def public_key(self, endpoint: str) -> str:
        """The key the agent at ``endpoint`` must hold ("" on an insecure rig)."""
        return self.server_keys.get(endpoint, b"").decode()

    def auth_refused(self) -> dict[str, int]:
        """What the authenticator refused, per socket."""
        return self.guard.refused if self.guard is not None else {}

    def request(self, endpoint: str, verb: str, timeout_ms: int = 1500) -> ControlReply | None:
        """One request to an agent: its reply (``ok`` or not), or None when none came in time.
        A reply that is not a valid EgoSurg reply to this request raises ``AgentReplyError``."""
        sock = self.ctx.socket(zmq.REQ)
        harden(sock, CONTROL_MAX_BYTES)
        sock.setsockopt(zmq.RCVTIMEO, timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, timeout_ms)
        request = ControlRequest(verb=verb)
        try:
            make_client(sock, self.security, self.server_keys.get(endpoint))
            sock.connect(endpoint)
            sock.send(request.to_bytes())
            raw = sock.recv()
        except zmq.Again:
            return None
        finally:
            sock.close(linger=0)
        return checked_reply(raw, request)


def checked_reply(raw: bytes, request: ControlRequest) -> ControlReply:
    """An agent's answer to ``request``; ``AgentReplyError`` names what is wrong with it."""
    try:
        reply = ControlReply.from_bytes(raw)
    except MalformedMessageError as exc:
        raise AgentReplyError("reply", f"is not a valid EgoSurg reply ({exc})") from None
    if reply.request_id != request.request_id:
        raise AgentReplyError(
            "request_id",
            f"answers request_id {reply.request_id[:40]!r}, not the request's "
            f"{request.request_id!r}; a reply must echo its request's request_id",
        )
    return reply


def receive_hwm(config: RigConfig, agent: AgentEndpoint) -> int:
    """``agent``'s SUB socket's high-water mark, in messages, from a byte budget.

    ZeroMQ bounds a queue in messages, so memory is bounded by counting every queued message at
    the largest legal frame message (``frame_message_max_bytes``: header and two images of
    ``max_image_bytes``, raw BGR at HD1200 unless rig.toml says less):

        hwm = min(receive_buffer_mb / agents / largest message,
                  RECEIVE_QUEUE_S * fps * the agent's cameras + 10 status messages)

    e.g. 1024 MB over 2 agents at 13.8 MB (raw HD1200) -> 37 messages (0.6 s of two cameras at
    30 fps); with ``max_image_bytes = 2000000`` (JPEG) 127 (2 s would take 130). The config
    refuses a budget under MIN_RECEIVE_MESSAGES per agent. A full queue leaves the backlog in
    the agent's send queue (the agent's memory), then the agent's PUB drops and ``seq`` counts
    the loss."""
    largest = frame_message_max_bytes(config.max_image_bytes)
    by_budget = int(config.receive_buffer_mb * 1e6 / max(len(config.agents), 1) // largest)
    cameras = len(agent.cameras) or 4  # an agent listed without cameras: a node's usual most
    by_time = math.ceil(RECEIVE_QUEUE_S * config.fps * cameras) + 10
    return max(1, min(by_budget, by_time))
