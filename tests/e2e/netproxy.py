"""A TCP proxy for fault tests: the one network link we may break on a test machine.

``TcpProxy(target_port)`` listens on a loopback port and forwards every connection to the
target, byte for byte (CURVE traffic passes untouched). ``pause()`` stops moving bytes in both
directions while the connections stay open, as a pulled cable does (TCP buffers fill, then the
peers' heartbeats give up); ``cut()`` also resets every connection and refuses new ones until
``resume()``, as a link that is down does.
"""

from __future__ import annotations

import logging
import select
import socket
import threading

log = logging.getLogger(__name__)

_CHUNK = 1 << 16


class TcpProxy:
    def __init__(self, target_port: int, target_host: str = "127.0.0.1") -> None:
        self.target = (target_host, target_port)
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.1)
        self.port = self._listener.getsockname()[1]
        self._flowing = threading.Event()
        self._flowing.set()
        self._refusing = False
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self.bytes_forwarded = 0
        self._thread = threading.Thread(target=self._accept, name="netproxy", daemon=True)
        self._thread.start()

    @property
    def address(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    def pause(self) -> None:
        """Stop forwarding; connections stay open."""
        self._flowing.clear()

    def cut(self) -> None:
        """Reset every connection and refuse new ones."""
        self._refusing = True
        self._flowing.clear()
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for a, b in pairs:
            for s in (a, b):
                _close(s, reset=True)

    def resume(self) -> None:
        self._refusing = False
        self._flowing.set()

    def close(self) -> None:
        self._closed.set()
        self._flowing.set()
        self._thread.join(timeout=5)
        self._listener.close()
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for a, b in pairs:
            _close(a)
            _close(b)

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self._refusing:
                _close(client, reset=True)
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2)
            except OSError:
                _close(client, reset=True)
                continue
            with self._lock:
                self._pairs.append((client, upstream))
            threading.Thread(
                target=self._pump, args=(client, upstream), name="netproxy-pump", daemon=True
            ).start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        peer = {a: b, b: a}
        try:
            while not self._closed.is_set():
                if not self._flowing.wait(0.1):
                    continue
                try:
                    readable, _, _ = select.select([a, b], [], [], 0.1)
                except (OSError, ValueError):
                    return  # cut() closed them
                for s in readable:
                    data = s.recv(_CHUNK)
                    if not data:
                        return
                    # while paused mid-chunk the bytes wait here, like a full link
                    self._flowing.wait()
                    peer[s].sendall(data)
                    self.bytes_forwarded += len(data)
        except OSError:
            return
        finally:
            _close(a)
            _close(b)
            with self._lock:
                if (a, b) in self._pairs:
                    self._pairs.remove((a, b))


def _close(s: socket.socket, reset: bool = False) -> None:
    try:
        if reset:  # RST instead of FIN: the peer sees the link fail, not a clean close
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        s.close()
    except OSError:
        pass
