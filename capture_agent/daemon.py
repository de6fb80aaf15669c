"""The run loop both daemons share: start, announce, run until SIGTERM/SIGINT, stop cleanly."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


def run_until_signal(
    start: Callable[[], None],
    stop: Callable[[], None],
    banner: str,
    healthy: Callable[[], bool] = lambda: True,
) -> int:
    """Run a daemon until SIGTERM or SIGINT (systemd's stop, or Ctrl-C); return its exit code.

    ``healthy`` is polled twice a second; when it turns false the daemon stops with code 1, so
    systemd restarts it instead of leaving a process that no longer works.
    """
    stopping = threading.Event()

    def _signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping cleanly", signum)
        stopping.set()

    signal.signal(signal.SIGTERM, _signal)
    signal.signal(signal.SIGINT, _signal)
    start()
    print(banner, flush=True)
    code = 0
    while not stopping.wait(0.5):
        if not healthy():
            log.error("a worker thread ended unexpectedly; exiting so the service restarts")
            code = 1
            break
    stop()
    return code
