"""Debian's ``chromium``, headless, driven through its DevTools protocol (a websocket): the real
browser the page tests use (``egosurg view``'s page, ``egosurg report``'s file). Every wait is
bounded; the process is ended by ``close``. ``make system-deps`` installs chromium; tests skip
without it (``CHROMIUM_MISSING``)."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

CHROMIUM_MISSING = shutil.which("chromium") is None
SKIP_REASON = "Debian's chromium is not installed (make system-deps installs it as root)"


class HeadlessChromium:
    """One headless chromium with one page; ``events`` keeps every DevTools event received
    (``Network.requestWillBeSent`` after ``call("Network.enable")``)."""

    def __init__(self, profile: Path, size_px: tuple[int, int] = (1280, 800)) -> None:
        self.proc = subprocess.Popen(
            ["chromium", "--headless=new", "--no-sandbox", "--use-gl=swiftshader",
             "--enable-unsafe-swiftshader", "--hide-scrollbars", "--no-first-run",
             f"--window-size={size_px[0]},{size_px[1]}", "--remote-debugging-port=0",
             "--remote-allow-origins=*", f"--user-data-dir={profile}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        found: list[str] = []

        def read_stderr() -> None:  # drains chromium's chatter so that it never blocks
            for line in self.proc.stderr or ():
                m = re.search(r"DevTools listening on (ws://\S+)", line)
                if m:
                    found.append(m.group(1))

        threading.Thread(target=read_stderr, daemon=True).start()
        deadline = time.monotonic() + 30
        while not found and time.monotonic() < deadline and self.proc.poll() is None:
            time.sleep(0.1)
        if not found:
            self.proc.kill()
            raise AssertionError("chromium did not start its DevTools endpoint within 30 s")
        http = found[0].replace("ws://", "http://").split("/devtools")[0]
        with urllib.request.urlopen(f"{http}/json/list", timeout=10) as reply:
            page = next(t for t in json.load(reply) if t["type"] == "page")
        from websockets.sync.client import connect

        self.ws = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        self._id = 0
        self.events: list[dict[str, Any]] = []

    def call(self, method: str, timeout_s: float = 30, **params):
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=timeout_s))
            if reply.get("id") == self._id:
                assert "error" not in reply, reply
                return reply["result"]
            if "method" in reply:
                self.events.append(reply)

    def wait_for(self, method: str, timeout_s: float = 30) -> dict[str, Any]:
        """The first event ``method`` received (before or after this call)."""
        deadline = time.monotonic() + timeout_s
        while True:
            for e in self.events:
                if e["method"] == method:
                    return e
            left = deadline - time.monotonic()
            assert left > 0, f"no {method} within {timeout_s} s"
            reply = json.loads(self.ws.recv(timeout=left))
            if "method" in reply:
                self.events.append(reply)

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return result["result"].get("value")

    def screenshot(self, full_page: bool = False) -> np.ndarray:
        """The page as (H, W, 3) uint8 RGB; ``full_page``: all of it, not just the viewport."""
        import cv2

        params: dict[str, Any] = {"format": "png"}
        if full_page:
            size = self.call("Page.getLayoutMetrics")["cssContentSize"]
            params |= {
                "captureBeyondViewport": True,
                "clip": {
                    "x": 0,
                    "y": 0,
                    "width": size["width"],
                    "height": size["height"],
                    "scale": 1,
                },
            }
        png = base64.b64decode(self.call("Page.captureScreenshot", **params)["data"])
        return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]

    def close(self) -> None:
        self.ws.close()
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
