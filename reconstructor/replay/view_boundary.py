"""Who may open ``egosurg view``'s case: the viewer's browser boundary.

Binding 127.0.0.1 keeps other machines out, not other web pages: any page open in the
reviewer's browser may open a websocket to 127.0.0.1:<port>, and a page whose name is made to
resolve to 127.0.0.1 (DNS rebinding) is, to the browser, on the viewer's own host. Viser serves
every websocket, so such a page could read the whole case (people included), press "Save
viewpoint" and send control values the page never would. A websocket is served only when its
opening request has all three of:

- **Origin** of the viewer's own page, ``http://127.0.0.1:<port>`` or ``http://localhost:<port>``
  (``http://[::1]:<port>`` too; for another bind address, that address). A browser always
  sends it and no page can set it.
- **Host** ``127.0.0.1:<port>`` or ``localhost:<port>`` (or the bind address): a rebinding page
  sends its own name.
- **The token**, as the websocket's path ``/<token>``: 32 random bytes
  (``secrets.token_urlsafe``) made at each start and carried by the URL ``egosurg view`` prints
  (``?websocket=ws://127.0.0.1:<port>/<token>``: viser's page takes its websocket address from
  that parameter). Whoever can read neither the terminal nor the browser's address bar cannot
  guess it.

Bound to a wildcard address (0.0.0.0, ::) the names the machine answers to are not known:
Origin must then be the page at the Host the request names, and the token keeps others out.

A refused connection is closed (1008, policy violation) before viser sends or reads a single
message, and the refusal is a counted warning line (``RareWarnings``). Only connections that
passed are trusted: "Save viewpoint" writes ``--save-to`` for no other, and each control value
a trusted page sends is checked by ``view_inputs`` before viser stores it. The HTTP page itself,
viser's client and no part of the case, is served to any request: what it shows comes only
through the websocket.

**The seams.** Viser (its range pinned in pyproject.toml) has no hook on the opening request.
Its websocket server (``viser.infra.WebsockServer``) runs its connection callbacks after the
handshake and before its senders and reader start, with the raw connection, request included,
in ``_live_connections``; the gate is one of those callbacks. Control updates reach viser's
``GuiApi._handle_gui_updates`` through the server's message handlers; the guard takes its
place and hands it only what passed. ``install`` stops the start with a ``ViewerError`` when a
viser upgrade has moved either seam (tests/reconstructor/test_view_boundary.py fails with it).
"""

from __future__ import annotations

import hmac
import logging
import secrets
from dataclasses import dataclass, field
from typing import Any

from reconstructor.errors import ViewerError
from reconstructor.replay.view_inputs import RareWarnings, clean_updates, shown

log = logging.getLogger(__name__)

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
POLICY_VIOLATION = 1008  # RFC 6455's close code for "the server's policy refuses this"
_INSTALL_VISER = "install the viser range egosurg lists: pip install -e '.[view]'"


def netloc(host: str) -> str:
    """A bind address as a URL writes it (IPv6 in brackets)."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


@dataclass(frozen=True, kw_only=True)
class Boundary:
    """The opening requests the viewer on ``port`` serves (module docstring)."""

    port: int
    token: str
    names: tuple[str, ...] | None  # host names a request may use; None: any (a wildcard bind)

    @classmethod
    def for_address(cls, host: str, port: int, token: str | None = None) -> Boundary:
        if host in WILDCARD_HOSTS:
            names: tuple[str, ...] | None = None
        elif host in ("127.0.0.1", "localhost", "::1"):
            names = LOOPBACK_NAMES
        else:
            names = (netloc(host).lower(),)
        return cls(port=port, token=token or secrets.token_urlsafe(32), names=names)

    def websocket_url(self, host: str) -> str:
        return f"ws://{netloc(host)}:{self.port}/{self.token}"

    def refusal(self, path: str, headers: Any) -> tuple[str, str] | None:
        """Why a websocket opened with ``path`` and ``headers`` (any mapping with
        ``get_all``, as websockets' Headers) is refused, as (kind, one line); None when it is
        served. The kind counts refusals: a page cannot make a new one with each request."""
        hosts, origins = headers.get_all("Host"), headers.get_all("Origin")
        if len(hosts) != 1:
            return "host", "no single Host header"
        host = hosts[0].lower()
        allowed = {host} if self.names is None else {f"{n}:{self.port}" for n in self.names}
        if host not in allowed:
            return "host", f"Host {shown(hosts[0])} is not this viewer's"
        if len(origins) != 1:
            return "origin", "no Origin header: not a page of this viewer"
        if origins[0].lower() not in {f"http://{h}" for h in allowed}:
            return "origin", f"Origin {shown(origins[0])} is not this viewer's page"
        if not hmac.compare_digest(path.encode(), f"/{self.token}".encode()):
            return "token", "no token or a wrong one: open the URL egosurg view printed"
        return None


@dataclass
class BrowserGate:
    """The boundary applied to a running viser server: ``install`` it once, right after the
    server starts; ``trusts`` says whether a client's connection passed."""

    boundary: Boundary
    trusted: set[int] = field(default_factory=set)
    warnings: RareWarnings = field(default_factory=lambda: RareWarnings(log))

    def trusts(self, client_id: int) -> bool:
        return client_id in self.trusted

    def install(self, server: Any) -> None:
        """Gate ``server`` (a ``viser.ViserServer``): connections, then control updates."""
        ws: Any = getattr(server, "_websock_server", None)
        if not isinstance(getattr(ws, "_live_connections", None), dict):
            raise ViewerError(f"this viser has no seam for the browser check: {_INSTALL_VISER}")
        connections: dict[int, Any] = ws._live_connections

        async def gate(conn: Any) -> None:
            raw = connections.get(conn.client_id)
            request = getattr(raw, "request", None)
            refused = (
                ("request", "no opening request") if request is None
                else self.boundary.refusal(request.path, request.headers)
            )  # fmt: skip
            if refused is None:
                self.trusted.add(conn.client_id)
                return
            kind, reason = refused
            self.warnings.warn(kind, "viewer: refused a browser connection: %s", reason)
            if raw is None:  # not with the pinned viser; raising makes websockets close it
                raise ConnectionRefusedError(reason)
            await raw.close(POLICY_VIOLATION, reason[:100])  # a close reason is <=123 bytes

        self._guard_gui_updates(server, ws)  # raises, like the check above, before any change
        ws.on_client_connect(gate)
        ws.on_client_disconnect(lambda conn: self.trusted.discard(conn.client_id))
        # a connection accepted before the gate was there is closed; the page reconnects,
        # through the gate
        ws.disconnect_all_clients()

    def _guard_gui_updates(self, server: Any, ws: Any) -> None:
        from viser import _messages

        message_cls = _messages.GuiUpdateMessage
        viser_handler = server.gui._handle_gui_updates
        handles: dict[str, Any] = server.gui._gui_input_handle_from_uuid
        try:
            ws.unregister_handler(message_cls, viser_handler)
        except (AssertionError, ValueError) as exc:
            raise ViewerError(
                f"this viser handles controls where the viewer cannot check them ({exc}): "
                f"{_INSTALL_VISER}"
            ) from None

        async def guarded(client_id: int, message: Any) -> None:
            if not self.trusts(client_id):
                self.warnings.warn("untrusted", "viewer: ignored a control from an unchecked page")
                return
            handle = handles.get(message.uuid)
            if handle is None:  # viser ignores a control it does not have
                return
            state = handle._impl
            try:
                updates = clean_updates(state.props.label, state.props, state.value,
                                        message.updates)  # fmt: skip
            except ValueError as exc:
                self.warnings.warn("refused", "viewer: refused a control value: %s", exc)
                return
            sent = message.updates.get("value")
            if updates["value"] != sent:
                self.warnings.warn("clamped", "viewer: clamped control %r's value %s to %s",
                                   state.props.label, shown(sent), updates["value"])  # fmt: skip
            await viser_handler(client_id, message_cls(uuid=message.uuid, updates=updates))

        ws.register_handler(message_cls, guarded)
