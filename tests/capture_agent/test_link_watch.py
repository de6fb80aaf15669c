"""A watched SUB link comes back by itself (capture_agent/link_watch.py), with real CURVE sockets
on loopback: a publisher whose ZAP handler refuses the subscriber's key until its allow-list is
fixed, and a publisher that sends one part over the subscriber's MAXMSGSIZE. libzmq alone never
reconnects after either; the watched link is made again, counted, and the cause named."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import zmq
from zmq.auth.thread import ThreadAuthenticator

from capture_agent.link_watch import DROPPED, HANDSHAKE_REFUSED, RECONNECTED, WatchedSub

MAX_PART_BYTES = 1000


class _AllowList:
    def __init__(self) -> None:
        self.keys: set[bytes] = set()

    def callback(self, domain: str, key: bytes) -> bool:
        return key in self.keys


@pytest.fixture
def publisher() -> Iterator[tuple[zmq.Socket, _AllowList, WatchedSub]]:
    """A CURVE PUB with an allow-list (empty at first) and a watched SUB of it."""
    ctx = zmq.Context()
    server_public, server_secret = zmq.curve_keypair()
    client_public, client_secret = zmq.curve_keypair()
    allow = _AllowList()
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve_callback("pub", credentials_provider=allow)
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.zap_domain = b"pub"
    pub.curve_secretkey, pub.curve_publickey = server_secret, server_public
    pub.curve_server = True
    port = pub.bind_to_random_port("tcp://127.0.0.1")

    def configure(sub: zmq.Socket) -> None:
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.MAXMSGSIZE, MAX_PART_BYTES)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.curve_secretkey, sub.curve_publickey = client_secret, client_public
        sub.curve_serverkey = server_public

    watched = WatchedSub(
        ctx, f"tcp://127.0.0.1:{port}", configure, who="test", max_part_bytes=MAX_PART_BYTES
    )
    allow.client_key = client_public  # type: ignore[attr-defined]
    try:
        yield pub, allow, watched
    finally:
        watched.close()
        pub.close(linger=0)
        auth.stop()
        ctx.term()


def _run(
    pub: zmq.Socket, watched: WatchedSub, seconds: float, until_received: int = 0
) -> tuple[int, list[str]]:
    """Publish and receive for ``seconds`` as the recorder's loop does (or until
    ``until_received`` messages came); (messages received, kinds of the link changes seen)."""
    got, kinds = 0, []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        kinds += [c.kind for c in watched.check()]
        if watched.due():
            watched.recreate()
        pub.send(b"frame")
        if watched.sock.poll(20):
            watched.sock.recv()
            got += 1
            if got == until_received:
                break
    return got, kinds


def test_a_refused_key_then_allowed_comes_back_without_a_new_subscriber(publisher):
    pub, allow, watched = publisher
    got, kinds = _run(pub, watched, 1.5)
    assert got == 0 and HANDSHAKE_REFUSED in kinds
    assert watched.counts.handshake_failures >= 1 and watched.counts.reconnects >= 1
    assert "refused this process's key" in watched.counts.last_cause
    allow.keys.add(allow.client_key)  # type: ignore[attr-defined]
    got, kinds = _run(pub, watched, 8.0, until_received=5)  # the backoff is at most 5 s
    assert got > 0 and RECONNECTED in kinds, watched.counts
    assert watched.counts.state == "up"


def test_one_part_over_the_limit_costs_the_link_a_moment_only(publisher):
    pub, allow, watched = publisher
    allow.keys.add(allow.client_key)  # type: ignore[attr-defined]
    got, _ = _run(pub, watched, 5.0, until_received=5)
    assert got > 0
    pub.send(b"x" * (MAX_PART_BYTES + 1))
    got, kinds = _run(pub, watched, 2.0)
    assert DROPPED in kinds and RECONNECTED in kinds, kinds
    assert got > 0 and watched.counts.drops == 1 and watched.counts.state == "up"
    assert "MAXMSGSIZE = 1000" in watched.counts.last_cause
    assert watched.counts.down_s < 2.0
