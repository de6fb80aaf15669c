"""Links that come back: a SUB socket watched by a ZeroMQ socket monitor, recreated when its link
drops or its handshake fails, and retried with backoff.

libzmq reconnects a SUB by itself after an ordinary disconnect, but not in two cases that a rig
meets: a peer that sent a part over ``MAXMSGSIZE`` (libzmq ends the session on EMSGSIZE) and a
CURVE handshake that was refused (the publisher's ZAP refused our key, or the publisher does not
hold the key we expect). Then the socket stays silent for good, and only a new socket connects
again. ``WatchedSub`` reads the socket's monitor events; after a drop or a failed handshake it
schedules a new socket (closed and made again with the same options, by the ``configure``
callback) ``RETRY_FIRST_S`` later, doubling up to ``RETRY_MAX_S`` while the link keeps failing
without a handshake in between. A new socket is not made while libzmq shows that it reconnects
by itself (``EVENT_CONNECT_RETRIED``/``EVENT_CONNECT_DELAYED`` after the drop: an ordinary
disconnect, or a publisher that is down), and a handshake that succeeds cancels the retry; a
drop that libzmq does not follow with a reconnect is one it ended itself, on a part over
``MAXMSGSIZE`` or a protocol error, and the cause says so.

Each change is counted (``LinkCounts``: state, drops, handshake failures, reconnects, the last
cause), logged (rate-limited) and returned by ``check`` as a ``LinkChange``, which the recorder
records as a session event while a take runs. Used by one thread only: the owner of the socket.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import zmq
from zmq.utils.monitor import parse_monitor_message

log = logging.getLogger(__name__)

RETRY_FIRST_S = 0.2  # the first new socket after a drop or a refused handshake
RETRY_MAX_S = 5.0  # the backoff doubles up to this while the link keeps failing
HANDSHAKE_FAILED = (
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)
RECONNECTING = zmq.EVENT_CONNECT_RETRIED | zmq.EVENT_CONNECT_DELAYED  # libzmq at it itself
WATCHED_EVENTS = (
    zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED | HANDSHAKE_FAILED | RECONNECTING
)

# the kinds of LinkChange
UP = "up"  # the link's first handshake
DROPPED = "dropped"
HANDSHAKE_REFUSED = "handshake_failed"
RECONNECTED = "reconnected"  # a handshake after a drop or failure: the link is back
RECREATED = "recreated"  # a new socket made (the cause: why)


def log_due(n: int) -> bool:
    """Whether the ``n``-th of a repeated event is logged: the first five, then every 100th."""
    return n <= 5 or n % 100 == 0


@dataclass(frozen=True, kw_only=True)
class LinkChange:
    """Something that happened to a watched link: ``kind`` (one of the constants above), when
    (Unix ns) and why, in words a user can act on."""

    kind: str
    time_unix_ns: int
    cause: str


@dataclass
class LinkCounts:
    """What ``status`` shows of one link."""

    state: str = "connecting"  # connecting, up, down (a new socket is due), retrying
    handshakes: int = 0  # handshakes that succeeded, the first one included
    drops: int = 0  # an up link that went down
    handshake_failures: int = 0  # handshakes refused by either side
    reconnects: int = 0  # new sockets made after a drop or a refused handshake
    last_cause: str = ""
    down_s: float = 0.0  # how long the link was down before it last came back

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "down_s": round(self.down_s, 2)}


class WatchedSub:
    """One SUB socket of ``endpoint``, made by ``configure`` (options and keys, before
    connect), with its monitor; ``check`` reads what happened, ``recreate`` makes it again."""

    def __init__(
        self,
        ctx: zmq.Context,
        endpoint: str,
        configure: Callable[[zmq.Socket], None],
        *,
        who: str,
        max_part_bytes: int,
    ) -> None:
        self.ctx = ctx
        self.endpoint = endpoint
        self.configure = configure
        self.who = who
        self.max_part_bytes = max_part_bytes
        self.counts = LinkCounts()
        self._retry_at: float | None = None  # monotonic s; a new socket is due then
        self._backoff_s = RETRY_FIRST_S
        self._down_since: float | None = None
        self._reconnecting = False  # libzmq showed it reconnects by itself since the last drop
        self.sock, self._monitor = self._open()

    def _open(self) -> tuple[zmq.Socket, zmq.Socket]:
        sock = self.ctx.socket(zmq.SUB)
        try:
            self.configure(sock)
            monitor = sock.get_monitor_socket(WATCHED_EVENTS)
            sock.connect(self.endpoint)
        except BaseException:
            sock.close(linger=0)
            raise
        return sock, monitor

    def close(self) -> None:
        self._close_socket()

    def _close_socket(self) -> None:
        try:
            self.sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._monitor.close(linger=0)
        self.sock.close(linger=0)

    def check(self, now: float | None = None) -> list[LinkChange]:
        """What the monitor reported since the last call (never waits)."""
        now = time.monotonic() if now is None else now
        changes = []
        while True:
            try:
                raw = self._monitor.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            try:
                event = parse_monitor_message(raw)
            except (ValueError, KeyError):
                continue
            change = self._on_event(int(event["event"]), event.get("value"), now)
            if change is not None:
                self._log(change)
                changes.append(change)
        return changes

    def due(self, now: float | None = None) -> bool:
        """Whether a new socket is due (``recreate``)."""
        now = time.monotonic() if now is None else now
        due = self._retry_at is not None and now >= self._retry_at
        return due and not self._reconnecting

    def recreate(self) -> LinkChange:
        """Close the socket (what it still queues is lost: drain it first) and make it again
        with the same options; returns the change, with the cause that led to it."""
        if self.counts.state == "down" and self.counts.last_cause.startswith(_DROP_CAUSE):
            self.counts.last_cause = (
                "libzmq ended the link and did not reconnect by itself: the publisher sent a "
                f"part over MAXMSGSIZE = {self.max_part_bytes} bytes (an image over "
                "max_image_bytes) or broke the protocol"
            )
        self._close_socket()
        self._retry_at = None
        self._reconnecting = False
        self.counts.reconnects += 1
        self.counts.state = "retrying"
        self.sock, self._monitor = self._open()
        change = LinkChange(
            kind=RECREATED,
            time_unix_ns=time.time_ns(),
            cause=f"new socket #{self.counts.reconnects} after: {self.counts.last_cause}",
        )
        self._log(change)
        return change

    # -- events ---------------------------------------------------------------------------------
    def _on_event(self, event: int, value: Any, now: float) -> LinkChange | None:
        c = self.counts
        if event & RECONNECTING:
            self._reconnecting = True
            return None
        if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
            c.handshakes += 1
            c.state = "up"
            self._retry_at = None
            self._backoff_s = RETRY_FIRST_S
            if c.handshakes == 1 and self._down_since is None:
                return self._change(UP, "first handshake with the publisher")
            c.down_s = now - self._down_since if self._down_since is not None else 0.0
            self._down_since = None
            return self._change(
                RECONNECTED,
                f"a new handshake with the publisher after {c.down_s:.1f} s down "
                f"({c.last_cause or 'the publisher restarted or was replaced'})",
            )
        if event & HANDSHAKE_FAILED:
            c.handshake_failures += 1
            return self._down(now, HANDSHAKE_REFUSED, _handshake_cause(event, value))
        if event == zmq.EVENT_DISCONNECTED:
            if c.state == "up":
                c.drops += 1
                return self._down(now, DROPPED, _DROP_CAUSE)
            if self._retry_at is None and c.state != "down":
                # closed before any handshake: the publisher refused us without saying so
                c.handshake_failures += 1
                return self._down(
                    now,
                    HANDSHAKE_REFUSED,
                    "the publisher closed the connection during the handshake (does it hold "
                    "the key rig.toml names for it?)",
                )
        return None

    def _down(self, now: float, kind: str, cause: str) -> LinkChange:
        c = self.counts
        c.state = "down"
        c.last_cause = cause
        self._reconnecting = False
        if self._down_since is None:
            self._down_since = now
        if self._retry_at is None:
            self._retry_at = now + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2, RETRY_MAX_S)
        return self._change(kind, cause)

    def _change(self, kind: str, cause: str) -> LinkChange:
        return LinkChange(kind=kind, time_unix_ns=time.time_ns(), cause=cause)

    def _log(self, change: LinkChange) -> None:
        c = self.counts
        n = {
            UP: 1,
            DROPPED: c.drops,
            HANDSHAKE_REFUSED: c.handshake_failures,
            RECONNECTED: c.handshakes,
            RECREATED: c.reconnects,
        }[change.kind]
        if not log_due(n):
            return
        level = logging.INFO if change.kind in (UP, RECONNECTED) else logging.WARNING
        log.log(
            level, "%s: link %s %s #%d: %s", self.who, self.endpoint, change.kind, n, change.cause
        )


_DROP_CAUSE = "the connection dropped (the publisher closed it, went away or broke the link)"


def _handshake_cause(event: int, value: Any) -> str:
    if event == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
        return (
            f"the publisher refused this process's key (ZAP status {value}): add its public "
            "key to the publisher's allowed keys, then restart the publisher"
        )
    if event == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
        return (
            f"the handshake broke the ZMTP/CURVE protocol (code {value}): the publisher is not "
            "an EgoSurg publisher of the key rig.toml names, or speaks plaintext"
        )
    return (
        f"the handshake failed (errno {value}): the publisher does not hold the key rig.toml "
        "names for it, or the connection broke mid-handshake"
    )
