"""CURVE on every ZeroMQ link: the rig's keys, who may connect, and hardened sockets.

Every link of the capture path is a ZeroMQ CURVE link (authenticated, encrypted, forward secret)
unless a config says ``insecure = true``. Each process has one keypair in pyzmq's certificate
format (``egosurg keys generate``: ``NAME.key`` holds the public key, ``NAME.key_secret`` both;
only the secret file is private, and it must be owner-only). A server socket (the agents' PUB and
REP, the recorder's control REP) accepts only the public keys of its allow-list: pyzmq's
``ThreadAuthenticator`` answers ZAP requests, one per context, with one ZAP domain per link. A
client socket (the recorder's SUB per agent, every REQ) knows the server's public key, so it
talks to that key or to nobody.

Refused attempts are logged (rate-limited) and counted per link: an unlisted key is refused by
ZAP (logged with the peer's address and key); a plaintext client, or one that speaks CURVE to the
wrong server key, fails the handshake (a socket monitor counts it). ``LinkGuard.refused`` is what
the daemons report in ``status``.

Every socket gets ``MAXMSGSIZE`` (per message part: a peer that sends a bigger part is
disconnected before it is buffered), a bounded handshake and TCP keepalive (not ZMTP heartbeats:
see ``KEEPALIVE_IDLE_S``), so a half-open or dead peer is dropped instead of held. A client's
link that drops or whose handshake is refused is made again by ``capture_agent/link_watch.py``.
"""

from __future__ import annotations

import logging
import os
import pwd
import stat
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils import z85
from zmq.utils.monitor import parse_monitor_message

from protocol.errors import ConfigError
from protocol.formats.security_config import (
    NO_KEYS,
    PUBLIC_SUFFIX,
    SECRET_SUFFIX,
    SecurityConfig,
)
from protocol.wire import MAX_JSON_BYTES

log = logging.getLogger(__name__)

CONTROL_MAX_BYTES = MAX_JSON_BYTES + 64  # one control JSON body (the limit of protocol/messages)
# What a PUB receives: subscriptions (we subscribe to b"") and the handshake. MAXMSGSIZE applies
# to ZMTP commands too, and CURVE's INITIATE (the client's vouch and metadata) is ~300 bytes.
SUBSCRIPTION_MAX_BYTES = 4096
HANDSHAKE_MS = 5000  # a peer that has not finished its handshake by then is dropped
# Dead peers are found by TCP keepalive, not ZMTP heartbeats: libzmq aborts the whole process
# (``Assertion failed: _input_stopped``, zeromq/libzmq#3937) when a heartbeat times out on a
# receiving socket whose queue is full, which is exactly what a stalling disk makes of the
# recorder's SUB sockets (tests/e2e/test_faults.py freezes the disk for 8 s).
KEEPALIVE_IDLE_S = 5
KEEPALIVE_INTERVAL_S = 2
KEEPALIVE_PROBES = 3
_LOG_EVERY = 1000  # after the first few, one log line per this many refusals of a link
_HANDSHAKE_FAILED = (
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)


# -- key files ----------------------------------------------------------------------------------
def _z85_key(value: bytes | None, path: Path, which: str) -> bytes:
    try:
        ok = value is not None and len(z85.decode(value)) == 32
    except (ValueError, KeyError, TypeError):
        ok = False
    if not ok:
        raise ConfigError(
            f"{path}: its {which} is not a CURVE key (40 Z85 characters); make keys with "
            "'egosurg keys generate --out DIR --name NAME'"
        )
    assert value is not None
    return value


def _read_certificate(path: Path, what: str) -> tuple[bytes | None, bytes | None]:
    # Opened here first because zmq says only "Invalid certificate file" for a file this user
    # may not read (keys made by 'sudo egosurg keys generate' without --owner).
    try:
        with open(path, "rb"):
            pass
    except PermissionError:
        raise ConfigError(_unreadable(path, what)) from None
    except (FileNotFoundError, NotADirectoryError):
        raise ConfigError(
            f"{what} {path} does not exist; make it with 'egosurg keys generate' or fix the "
            "path in the config"
        ) from None
    except OSError as exc:
        raise ConfigError(f"{what} {path} cannot be read as a key file: {exc}") from None
    try:
        return zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{what} {path} cannot be read as a key file: {exc}") from None


def _unreadable(path: Path, what: str) -> str:
    try:
        user = pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:  # a uid without a passwd entry (a container)
        user = f"uid {os.geteuid()}"
    return (
        f"{what} {path} cannot be read by user {user}: make the key owned by that user "
        f"('sudo chown {user}: {path}' and let it enter the folder), or make new keys with "
        f"'sudo egosurg keys generate --owner {user} --out DIR --name NAME'"
    )


def check_secret_mode(path: Path) -> None:
    """Refuse a secret key file that group or others may read or write."""
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise ConfigError(
            f"secret key file {path} has mode {mode:04o}: group or others may read it. "
            f"Run 'chmod 600 {path}' (and keep it owned by the service's user)"
        )


def load_public_key(path: Path | str, what: str = "public key file") -> bytes:
    """The Z85 public key of a ``.key`` (or ``.key_secret``) file."""
    p = Path(path)
    public, _ = _read_certificate(p, what)
    return _z85_key(public, p, "public-key")


def load_keypair(path: Path | str, what: str = "secret key file") -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys of a ``.key_secret`` file that only its owner can read."""
    p = Path(path)
    public, secret = _read_certificate(p, what)
    if secret is None:
        raise ConfigError(
            f"{what} {p} holds no secret key (is it the public {PUBLIC_SUFFIX} file? use the "
            f"{SECRET_SUFFIX} file)"
        )
    check_secret_mode(p)
    secret = _z85_key(secret, p, "secret-key")
    public = _z85_key(public, p, "public-key")
    if zmq.curve_public(secret) != public:
        raise ConfigError(f"{p}: its public key does not belong to its secret key; regenerate it")
    return public, secret


# -- what a config says, and what a process loads -----------------------------------------------
@dataclass(frozen=True, kw_only=True)
class LinkSecurity:
    """How this process's links are secured: its keypair and who may connect to its servers.

    ``insecure`` means plaintext links (NULL mechanism) that anyone who can reach the ports may
    use; it is only ever set by an explicit ``insecure = true``.
    """

    insecure: bool = False
    public_key: bytes = b""  # Z85
    secret_key: bytes = b""  # Z85; never logged, never stored in a session
    allowed_keys: frozenset[bytes] = frozenset()  # Z85 public keys allowed to connect
    key_file: str = ""

    def __post_init__(self) -> None:
        if not self.insecure and not (self.public_key and self.secret_key):
            raise ConfigError("a secure link needs this process's keypair")

    def __repr__(self) -> str:  # keep the secret out of logs and tracebacks
        return (
            f"LinkSecurity(insecure={self.insecure}, public_key={self.public_key!r}, "
            f"allowed_keys={len(self.allowed_keys)}, key_file={self.key_file!r})"
        )

    @classmethod
    def plaintext(cls) -> LinkSecurity:
        return cls(insecure=True)

    @classmethod
    def load(cls, secret_key_file: str, allowed_key_files: tuple[str, ...] = ()) -> LinkSecurity:
        public, secret = load_keypair(secret_key_file)
        allowed = frozenset(
            load_public_key(p, "allowed public key file") for p in allowed_key_files
        )
        return cls(
            public_key=public, secret_key=secret, allowed_keys=allowed, key_file=secret_key_file
        )

    @classmethod
    def from_config(cls, config: SecurityConfig) -> LinkSecurity:
        """A daemon's ``[security]`` keys, loaded (ConfigError when missing, unreadable or not
        0600)."""
        if config.insecure:
            return cls.plaintext()
        if not config.secret_key or not config.peer_keys:
            raise ConfigError(f"{config.where or 'config'}: no CURVE keys; {NO_KEYS}")
        return cls.load(config.secret_key, config.peer_keys)


def warn_insecure(who: str) -> None:
    """Logged at every start of a process whose links are plaintext."""
    log.warning(
        "%s: INSECURE links (insecure = true): no authentication, no encryption; anyone who "
        "reaches these ports can control the rig and watch its video. Make keys with "
        "'egosurg keys generate' and remove insecure = true",
        who,
    )


# -- sockets ------------------------------------------------------------------------------------
def harden(sock: zmq.Socket, max_message_bytes: int) -> None:
    """Options every socket of the capture path gets."""
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, max_message_bytes)
    sock.setsockopt(zmq.HANDSHAKE_IVL, HANDSHAKE_MS)
    sock.setsockopt(zmq.TCP_KEEPALIVE, 1)
    sock.setsockopt(zmq.TCP_KEEPALIVE_IDLE, KEEPALIVE_IDLE_S)
    sock.setsockopt(zmq.TCP_KEEPALIVE_INTVL, KEEPALIVE_INTERVAL_S)
    sock.setsockopt(zmq.TCP_KEEPALIVE_CNT, KEEPALIVE_PROBES)


def make_client(sock: zmq.Socket, links: LinkSecurity, server_key: bytes | None) -> None:
    """A CURVE client of the server whose public key is ``server_key`` (before connect)."""
    if links.insecure:
        return
    if not server_key:
        raise ConfigError("a secure link needs the public key of the server it connects to")
    sock.curve_secretkey = links.secret_key
    sock.curve_publickey = links.public_key
    sock.curve_serverkey = server_key


class _Authenticator(ThreadAuthenticator):
    """pyzmq's authenticator, remembering the peer address of the request being answered (ZAP
    frame 4, RFC 27) so a refusal can name where it came from."""

    peer_address = ""

    async def handle_zap_message(self, msg: list[bytes]) -> None:
        self.peer_address = msg[3].decode("utf-8", "replace") if len(msg) > 3 else "?"
        await super().handle_zap_message(msg)


@dataclass
class _Domain:
    allowed: frozenset[bytes]
    refused: int = 0
    refused_keys: set[bytes] = field(default_factory=set)


class LinkGuard:
    """One per daemon (per ZeroMQ context): its authenticator, allow-lists and refusal counts.

    ``make_server`` makes a socket a CURVE server whose allow-list is checked under its own ZAP
    domain; ``refused`` counts refused connection attempts per domain.
    """

    def __init__(self, ctx: zmq.Context, links: LinkSecurity, who: str) -> None:
        self.ctx = ctx
        self.links = links
        self.who = who
        self._lock = threading.Lock()
        self._domains: dict[str, _Domain] = {}
        self._auth: _Authenticator | None = None
        self._monitors: dict[zmq.Socket, str] = {}
        self._monitor_thread: threading.Thread | None = None
        self._closing = threading.Event()
        if links.insecure:
            warn_insecure(who)

    def make_server(
        self, sock: zmq.Socket, domain: str, allowed: frozenset[bytes] | None = None
    ) -> None:
        """Before bind: a CURVE server accepting ``allowed`` (default: the links' allow-list)."""
        keys = self.links.allowed_keys if allowed is None else allowed
        with self._lock:
            self._domains[domain] = _Domain(allowed=frozenset(keys))
        if self.links.insecure:
            return
        if self._auth is None:
            # must run before the first bind: without a ZAP handler, libzmq lets every key in
            self._auth = _Authenticator(self.ctx, log=logging.getLogger(f"{__name__}.zap"))
            self._auth.start()
        self._auth.configure_curve_callback(domain, credentials_provider=self)
        sock.zap_domain = domain.encode()
        sock.curve_secretkey = self.links.secret_key
        sock.curve_publickey = self.links.public_key
        sock.curve_server = True
        self._monitor(sock, domain)

    # pyzmq's credentials-provider interface, called in the authenticator's thread
    def callback(self, domain: str, key: bytes) -> bool:
        with self._lock:
            d = self._domains.get(domain)
            if d is not None and key in d.allowed:
                return True
        peer = self._auth.peer_address if self._auth is not None else "?"
        self._refused(domain, f"unlisted key {key.decode('ascii', 'replace')} from {peer}", key)
        return False

    def _refused(self, domain: str, why: str, key: bytes | None = None) -> None:
        with self._lock:
            d = self._domains.setdefault(domain, _Domain(allowed=frozenset()))
            d.refused += 1
            n = d.refused
            new_key = key is not None and key not in d.refused_keys and len(d.refused_keys) < 64
            if new_key:
                d.refused_keys.add(key)  # type: ignore[arg-type]
        if n <= 5 or new_key or n % _LOG_EVERY == 0:
            log.warning("%s: refused connection #%d on %s: %s", self.who, n, domain, why)

    @property
    def refused(self) -> dict[str, int]:
        """Refused connection attempts per link (ZAP domain)."""
        with self._lock:
            return {name: d.refused for name, d in self._domains.items()}

    @property
    def refused_total(self) -> int:
        return sum(self.refused.values())

    # -- handshake failures (plaintext peers, wrong server key) ---------------------------------
    def _monitor(self, sock: zmq.Socket, domain: str) -> None:
        mon = sock.get_monitor_socket(_HANDSHAKE_FAILED)
        with self._lock:
            self._monitors[mon] = domain
        if self._monitor_thread is None:
            self._monitor_thread = threading.Thread(
                target=self._watch, name=f"link-guard-{self.who}", daemon=True
            )
            self._monitor_thread.start()

    def _watch(self) -> None:
        while not self._closing.is_set():
            with self._lock:
                socks = list(self._monitors)
            if not socks:
                self._closing.wait(0.1)
                continue
            poller = zmq.Poller()
            for s in socks:
                poller.register(s, zmq.POLLIN)
            for s, _ in poller.poll(100):
                try:
                    event = parse_monitor_message(s.recv_multipart(zmq.NOBLOCK))
                except (zmq.ZMQError, ValueError):
                    continue
                self._on_event(self._monitors[s], event)
        with self._lock:
            for s in self._monitors:
                s.close(linger=0)
            self._monitors.clear()

    def _on_event(self, domain: str, event: Mapping[str, Any]) -> None:
        if event["event"] == zmq.EVENT_HANDSHAKE_FAILED_AUTH or not (
            event["event"] & _HANDSHAKE_FAILED
        ):
            return  # an unlisted key is counted and logged by the ZAP callback
        self._refused(
            domain,
            "handshake failed: a plaintext client, a CURVE client of another server key, or a "
            f"connection broken mid-handshake (event {event['event']}, value {event['value']})",
        )

    def close(self) -> None:
        """Stop the authenticator and the monitor (after the guarded sockets are closed)."""
        self._closing.set()
        if self._monitor_thread is not None:
            self._monitor_thread.join(timeout=2.0)
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
