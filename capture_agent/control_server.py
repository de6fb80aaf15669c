"""The control socket's request handling, shared by the recorder and the agent.

Example::

    server = ControlServer("recorder or-3", handle)   # handle(ControlRequest) -> result dict
    while running:
        if rep.poll(100):
            server.serve(rep)                          # one request in, exactly one reply out

Whatever arrives, the peer gets exactly one reply and the daemon goes on:

- a request that cannot be read (not one part, not UTF-8 JSON, another wire version, an unknown
  verb, a missing or overlong field) gets ``ok: false`` with the reason; its ``request_id`` is
  the request's own where one can be read, else empty (the spec allows that in error replies);
- a refusal (``Refused``, e.g. a start without PTP lock) gets ``ok: false`` with its message;
- a bug in a handler gets ``ok: false``, "internal error ..." and a log line with the traceback;
- a result too large for one message (``MAX_JSON_BYTES``) gets an error saying so.

Error texts are escaped and cut to ``MAX_ERROR_CHARS``, and messages quote input through
``protocol.safe_text.brief``, so a reply never echoes unbounded input. The REP socket is read
with ``recv_multipart``: a request of several parts is answered (with an error), never left
half-read, which would put the socket in the wrong state (``EFSM``) for its reply. Counts of
every outcome are in ``counts()``, which the daemons report in ``status``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any

import zmq

from capture_agent.errors import Refused
from protocol.safe_text import brief, safe_text
from protocol.wire import (
    MAX_JSON_BYTES,
    ControlReply,
    ControlRequest,
    MalformedMessageError,
    UnknownVersionError,
)

log = logging.getLogger(__name__)

MAX_ERROR_CHARS = 2000  # an error reply's text; reasons are a few lines at most
_LOG_FIRST = 5  # log the first few rejections of each kind, then one in _LOG_EVERY
_LOG_EVERY = 1000
# The reply of last resort, built once: it cannot fail when everything else has.
_LAST_RESORT = ControlReply(
    ok=False,
    error="internal error while answering; the daemon goes on, see its log",
    request_id="",
).to_bytes()


Handler = Callable[[ControlRequest], dict[str, Any]]


class ControlServer:
    """Answers the requests of one control socket with ``handle``; never raises."""

    def __init__(self, name: str, handle: Handler) -> None:
        self.name = name
        self.handle = handle
        self._counts = dict.fromkeys(
            (
                "requests",
                "answered_ok",
                "refused",
                "rejected_malformed",
                "rejected_unknown_version",
                "internal_errors",
                "replies_too_large",
                "send_failed",
            ),
            0,
        )

    def counts(self) -> dict[str, int]:
        """Every outcome so far: ``requests`` = ``answered_ok`` + ``refused`` + rejections +
        ``internal_errors`` + ``replies_too_large``."""
        return dict(self._counts)

    @property
    def rejected(self) -> int:
        """Requests that could not be read at all."""
        return self._counts["rejected_malformed"] + self._counts["rejected_unknown_version"]

    # -- the socket -----------------------------------------------------------------------------
    def serve(self, sock: zmq.Socket) -> bool:
        """Receive one waiting request on the REP ``sock`` and send its reply; False when none
        was waiting. Never raises but for a closed socket or context (the daemon is stopping)."""
        try:
            parts = sock.recv_multipart(zmq.NOBLOCK)
        except zmq.Again:
            return False
        except zmq.ZMQError as exc:
            if exc.errno in (zmq.ETERM, zmq.ENOTSOCK):
                raise
            # EFSM: a reply is owed (it cannot happen with one reply per recv_multipart, but
            # a socket stuck waiting to reply would refuse every later request): answer it.
            log.error("%s: control socket: %s; sending an error reply to recover", self.name, exc)
            self._send(sock, _LAST_RESORT)
            return False
        self._send(sock, self.answer(parts))
        return True

    def _send(self, sock: zmq.Socket, data: bytes) -> None:
        try:
            sock.send(data, zmq.NOBLOCK)
        except zmq.ZMQError as exc:
            if exc.errno in (zmq.ETERM, zmq.ENOTSOCK):
                raise
            # REP drops replies to peers that left; anything else is logged and counted
            self._counts["send_failed"] += 1
            log.warning("%s: control reply not sent: %s", self.name, exc)

    # -- one request ----------------------------------------------------------------------------
    def answer(self, parts: list[bytes]) -> bytes:
        """The encoded reply to one received request (its parts); never raises."""
        try:
            return self._answer(parts)
        except Exception:  # the last line of defence: a reply must go out
            self._counts["internal_errors"] += 1
            log.exception("%s: answering a control request failed", self.name)
            return _LAST_RESORT

    def _answer(self, parts: list[bytes]) -> bytes:
        self._counts["requests"] += 1
        try:
            req = _decode(parts)
        except UnknownVersionError as exc:
            return self._reject("rejected_unknown_version", exc, parts)
        except MalformedMessageError as exc:
            return self._reject("rejected_malformed", exc, parts)
        try:
            result = self.handle(req)
        except Refused as exc:
            self._counts["refused"] += 1
            log.info("%s: refused %s: %s", self.name, req.verb, safe_text(exc, MAX_ERROR_CHARS))
            return self._error(str(exc), req.request_id)
        except Exception as exc:  # a bug in a handler must not take the daemon down mid-case
            self._counts["internal_errors"] += 1
            log.exception("%s: control %s failed", self.name, req.verb)
            return self._error(
                f"internal error in '{req.verb}': {brief(exc)}; the daemon goes on, see its log",
                req.request_id,
            )
        try:
            data = ControlReply(ok=True, result=result, request_id=req.request_id).to_bytes()
        except MalformedMessageError as exc:  # too large, or not JSON: a bug, answered
            self._counts["replies_too_large"] += 1
            log.error("%s: the reply to %s cannot be sent: %s", self.name, req.verb, exc)
            return self._error(
                f"the reply to '{req.verb}' cannot be sent ({safe_text(exc, 300)}; at most "
                f"{MAX_JSON_BYTES} bytes of JSON); this is a bug, please report it with the log",
                req.request_id,
            )
        self._counts["answered_ok"] += 1
        return data

    def _reject(self, kind: str, exc: MalformedMessageError, parts: list[bytes]) -> bytes:
        self._counts[kind] += 1
        n = self._counts[kind]
        if n <= _LOG_FIRST or n % _LOG_EVERY == 0:
            log.warning(
                "%s: rejected control request #%d (%s): %s",
                self.name,
                n,
                kind,
                safe_text(exc, 300),
            )
        return self._error(f"request rejected: {exc}", _salvage_request_id(parts))

    def _error(self, text: str, request_id: str) -> bytes:
        error = safe_text(text, MAX_ERROR_CHARS).strip() or "refused (no reason given)"
        return ControlReply(ok=False, error=error, request_id=request_id).to_bytes()


def _decode(parts: list[bytes]) -> ControlRequest:
    if len(parts) != 1:
        raise MalformedMessageError(
            f"control request has {len(parts)} parts, expected 1 (one JSON ControlRequest)"
        )
    return ControlRequest.from_bytes(parts[0])


def _salvage_request_id(parts: list[bytes]) -> str:
    """The ``request_id`` of a request that could not be read, where it is a valid id: the
    peer can then match the error to its request. Empty otherwise."""
    if len(parts) != 1 or len(parts[0]) > MAX_JSON_BYTES:
        return ""
    try:
        d = json.loads(parts[0].decode("utf-8"))
        rid = d.get("request_id", "") if isinstance(d, dict) else ""
        # the reply's own check, and its encoding: JSON can spell a lone surrogate that no
        # UTF-8 reply can carry
        ControlReply(ok=False, error="x", request_id=rid).to_bytes()
    except (ValueError, RecursionError, AttributeError, UnicodeError):
        return ""
    return rid
