"""The run loop both daemons share: start, tell systemd, watch progress, stop cleanly.

Example::

    progress = Progress("io")                     # the daemon's loops call progress.beat("io")
    code = run_until_signal(start, stop, "egosurg recorder or-3 ...",
                            progress=progress.ages_s, stall_limit_s=20.0)

Progress, not liveness: each loop of a daemon records a monotonic heartbeat every iteration
(``Progress.beat``). A thread that is alive but stuck (a hung call, an endless inner loop) stops
beating; when any loop's last beat is older than ``stall_limit_s`` the daemon stops with exit
code 1, so systemd restarts it.

The systemd notify protocol (``sd_notify(3)``), spoken directly: one datagram per message to
the ``AF_UNIX`` socket named by ``$NOTIFY_SOCKET`` (a leading ``@`` means the abstract
namespace), each a newline-separated list of ``KEY=VALUE``:

1. ``READY=1`` and ``STATUS=<banner>`` once ``start`` has returned (``Type=notify``);
2. every half of ``$WATCHDOG_USEC`` (set by ``WatchdogSec=``), ``WATCHDOG=1``, but only while
   every loop's progress is fresh: a stalled daemon falls silent and systemd kills it even if
   this thread could not end it;
3. ``STATUS=<status_line()>`` every ``STATUS_EVERY_S`` and when it changes;
4. ``STATUS=<why>`` when a loop stalls, and ``STOPPING=1`` before ``stop``.

Without ``$NOTIFY_SOCKET`` (run by hand) nothing is sent.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

TICK_S = 0.5  # how often progress is checked (and the fastest watchdog ping)
STATUS_EVERY_S = 10.0


class Progress:
    """Monotonic heartbeats of a daemon's loops; each loop calls ``beat(name)`` every
    iteration. Names given at construction count from then, so a loop that never ran stalls."""

    def __init__(self, *names: str) -> None:
        now = time.monotonic()
        self._last: dict[str, float] = dict.fromkeys(names, now)

    def beat(self, name: str) -> None:
        self._last[name] = time.monotonic()  # one dict store: safe across threads

    def ages_s(self) -> dict[str, float]:
        """Seconds since each loop last made progress."""
        now = time.monotonic()
        return {name: round(now - t, 3) for name, t in list(self._last.items())}


class SystemdNotifier:
    """``sd_notify`` over ``$NOTIFY_SOCKET``; does nothing when the variable is not set."""

    def __init__(self, environ: Mapping[str, str] = os.environ) -> None:
        self.address: str | None = None
        self.watchdog_interval_s: float | None = None
        self._sock: socket.socket | None = None
        path = environ.get("NOTIFY_SOCKET", "")
        if path.startswith(("/", "@")):
            self.address = "\0" + path[1:] if path.startswith("@") else path
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # A receiver that does not read (its queue holds net.unix.max_dgram_qlen datagrams)
            # must not block the daemon: a message that does not fit is dropped.
            self._sock.setblocking(False)
        elif path:
            log.warning("NOTIFY_SOCKET=%r is not a unix socket path; not notifying systemd", path)
        usec = environ.get("WATCHDOG_USEC", "")
        pid = environ.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval_s = int(usec) / 2e6  # ping at half the limit, as systemd asks

    def notify(self, *fields: str) -> None:
        if self._sock is None or self.address is None:
            return
        try:
            self._sock.sendto("\n".join(fields).encode("utf-8", "replace"), self.address)
        except OSError as exc:  # systemd gone or the socket full: keep running
            log.debug("sd_notify failed: %s", exc)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _one_line(text: str) -> str:
    return " ".join(text.split())[:400]


def run_until_signal(
    start: Callable[[], None],
    stop: Callable[[], None],
    banner: str,
    *,
    progress: Callable[[], Mapping[str, float]] = dict,
    stall_limit_s: float = 30.0,
    status_line: Callable[[], str] | None = None,
    healthy: Callable[[], bool] = lambda: True,
) -> int:
    """Run a daemon until SIGTERM or SIGINT (systemd's stop, or Ctrl-C); return its exit code.

    ``progress`` gives each loop's seconds since its last progress; past ``stall_limit_s``,
    or when ``healthy`` turns false (a thread ended), the daemon stops with code 1 so that
    systemd restarts it instead of keeping a process that no longer works.
    """
    stopping = threading.Event()

    def _signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping cleanly", signum)
        stopping.set()

    previous = {s: signal.signal(s, _signal) for s in (signal.SIGTERM, signal.SIGINT)}
    notifier = SystemdNotifier()
    try:
        start()
        print(banner, flush=True)
        notifier.notify("READY=1", f"STATUS={_one_line(banner)}")
        code = _watch(stopping, notifier, progress, stall_limit_s, status_line, healthy)
        notifier.notify("STOPPING=1")
        stop()
        return code
    finally:
        notifier.close()
        for s, handler in previous.items():
            signal.signal(s, handler)


def _watch(
    stopping: threading.Event,
    notifier: SystemdNotifier,
    progress: Callable[[], Mapping[str, float]],
    stall_limit_s: float,
    status_line: Callable[[], str] | None,
    healthy: Callable[[], bool],
) -> int:
    tick = TICK_S
    if notifier.watchdog_interval_s is not None:
        tick = min(tick, notifier.watchdog_interval_s)
    last_status, last_status_at = "", 0.0
    while not stopping.wait(tick):
        ages = dict(progress())
        stalled = {name: age for name, age in ages.items() if age > stall_limit_s}
        if stalled or not healthy():
            why = (
                "no progress in "
                + ", ".join(f"{name} for {age:.1f} s" for name, age in sorted(stalled.items()))
                + f" (limit {stall_limit_s:g} s)"
                if stalled
                else "a worker thread ended unexpectedly"
            )
            log.error("%s; exiting so that the service restarts", why)
            notifier.notify(f"STATUS=stalled: {why}; restarting")
            return 1
        if notifier.watchdog_interval_s is not None:
            notifier.notify("WATCHDOG=1")
        if status_line is not None:
            try:
                line = _one_line(status_line())
            except Exception:  # a status line is informational; never stop the daemon for it
                log.debug("status line failed", exc_info=True)
                continue
            now = time.monotonic()
            if line != last_status or now - last_status_at >= STATUS_EVERY_S:
                notifier.notify(f"STATUS={line}")
                last_status, last_status_at = line, now
    return 0
