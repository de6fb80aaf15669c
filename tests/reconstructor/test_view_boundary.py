"""``egosurg view``'s browser boundary (reconstructor/replay/view_boundary.py, view_inputs.py).

The viewer listens on 127.0.0.1, but every page open in the reviewer's browser can reach
127.0.0.1 too. What a user relies on, tried with a real websocket client against a real viewer:

- only the viewer's own page gets the case: a foreign Origin, a foreign Host (a DNS-rebinding
  page), or a missing or wrong token gets no byte of the scene, and what it sends is never read
  (so it cannot append viewpoints to ``--save-to``);
- the URL that ``egosurg view`` prints carries the token, and the page opened at it connects;
- a value the page's controls could never send (1e308, NaN, inf, a huge string, a forged
  maximum or label) is clamped or refused before viser stores it, and the next browser still
  gets the whole scene.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from protocol.formats.trajectory import Keyframe, Trajectory, write_trajectories
from tests.helpers import REPO

viser = pytest.importorskip("viser", reason="egosurg view needs viser: pip install -e '.[dev]'")

from reconstructor.replay.view import CaseViewer, ViewConfig  # noqa: E402
from tests.reconstructor.test_view import (  # noqa: E402
    TIMES_S,
    RawBrowser,
    gui_uuid,
    make_case,
    websocket_url,
)

SCENE_BYTES = 100_000  # the wall's splats alone: 4,000 x 32 bytes


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    return make_case(tmp_path_factory.mktemp("boundary") / "case")


@pytest.fixture()
def viewer(case, tmp_path):
    roles = tmp_path / "roles.toml"
    write_trajectories(roles, [Trajectory(name="surgeon", keyframes=(
        Keyframe(time_s=TIMES_S[0], eye_m=(0.5, -1.5, 1.7), look_at_m=(0.0, 0.0, 1.0)),
    ))])  # fmt: skip
    v = CaseViewer(case, ViewConfig(port=0, roles=roles, save_to=tmp_path / "viewpoints.toml"))
    yield v
    v.close()


def refused(browser: RawBrowser, seconds: float = 10.0) -> bool:
    """True when the server closes the connection without sending a single message."""
    from websockets.exceptions import ConnectionClosed

    try:
        browser.ws.recv(timeout=seconds)
    except ConnectionClosed:
        return True
    except TimeoutError:
        return False
    return False


def attempt(viewer, **kwargs) -> bool:
    """Whether a connection made with ``kwargs`` (RawBrowser's) is refused: at the handshake,
    or closed before the scene."""
    from websockets.exceptions import InvalidHandshake

    try:
        browser = RawBrowser(viewer, **kwargs)
    except InvalidHandshake:
        return True
    try:
        return refused(browser)
    finally:
        browser.close()


def camera_message() -> dict:
    """What the page sends first: viser counts a browser in on its first camera."""
    return {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0),
            "position": (0.0, -3.0, 1.0), "fov": 0.9, "near": 0.01, "far": 100.0,
            "image_height": 400, "image_width": 640, "look_at": (0.0, 0.0, 1.0),
            "up_direction": (0.0, 0.0, 1.0)}  # fmt: skip


def test_only_the_viewers_own_page_with_its_token_gets_the_case(viewer):
    port = viewer.server.get_port()
    url = websocket_url(viewer)
    token = urllib.parse.urlsplit(url).path.strip("/")
    assert len(token) >= 32  # secrets.token_urlsafe(32): 43 characters
    own = f"http://127.0.0.1:{port}"
    assert attempt(viewer, origin="http://evil.example")
    assert attempt(viewer, origin=f"http://evil.example:{port}")
    assert attempt(viewer, origin="null")  # a sandboxed frame or a file:// page
    assert attempt(viewer, origin=None)
    assert attempt(viewer, origin=f"http://127.0.0.1:{port + 1}")
    # DNS rebinding: a page whose name resolves to 127.0.0.1 sends its own name as the Host
    assert attempt(viewer, origin=f"http://evil.example:{port}", host=f"evil.example:{port}")
    assert attempt(viewer, origin=own, host=f"evil.example:{port}")
    for path in ("/", f"/{token[:-1]}", f"/{token}x", f"/{token}/x", f"/?token={token}"):
        assert attempt(viewer, url=f"ws://127.0.0.1:{port}{path}"), path
    for origin, host in ((own, None), (f"http://localhost:{port}", f"localhost:{port}")):
        browser = RawBrowser(viewer, origin=origin, host=host)
        assert browser.received_bytes(3.0) > SCENE_BYTES, origin
        browser.close()


def test_a_page_without_the_token_cannot_save_a_viewpoint(viewer):
    from websockets.exceptions import ConnectionClosed

    save = gui_uuid(viewer, "Save viewpoint")
    foreign = RawBrowser(viewer, origin="http://evil.example")
    tokenless = RawBrowser(viewer, url=f"ws://127.0.0.1:{viewer.server.get_port()}/")
    for browser in (foreign, tokenless):
        try:
            browser.send(camera_message())
            browser.send({"type": "GuiUpdateMessage", "uuid": save, "updates": {"value": True}})
        except ConnectionClosed:  # already closed by the server: what we want
            pass
        assert refused(browser)
        browser.close()
    time.sleep(1.0)  # a save, had either been read, runs on viser's threads within this
    assert not viewer.config.save_to.exists()
    own = RawBrowser(viewer)  # the token's page saves
    own.received_bytes(1.0)
    own.send(camera_message())
    own.send({"type": "GuiUpdateMessage", "uuid": save, "updates": {"value": True}})
    deadline = time.monotonic() + 10
    while not viewer.config.save_to.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    own.close()
    assert viewer.config.save_to.exists()


def shows(viewer, t_s: float) -> bool:
    """Whether the viewer comes to show ``t_s`` within 10 s (viser runs updates on its loop)."""
    deadline = time.monotonic() + 10
    while viewer.entry.t_s != t_s and time.monotonic() < deadline:
        time.sleep(0.05)
    return viewer.entry.t_s == t_s


def test_forged_control_values_are_clamped_and_the_next_browser_gets_the_scene(viewer, caplog):
    """Today's failure: with the last timestamp shown, a slider sent to 1e308 was stored as a
    309-digit integer that viser's encoder cannot write, and no browser got the scene again."""
    caplog.set_level("INFO")
    first = RawBrowser(viewer)
    scene_bytes = first.received_bytes(3.0)
    assert scene_bytes > SCENE_BYTES
    first.send(camera_message())
    slider, role = gui_uuid(viewer, "Case time (s)"), gui_uuid(viewer, "Role")
    first.send({"type": "GuiUpdateMessage", "uuid": slider, "updates": {"value": TIMES_S[-1]}})
    assert shows(viewer, TIMES_S[-1])
    first.send({"type": "GuiUpdateMessage", "uuid": slider, "updates": {"value": 1e308}})
    first.received_bytes(1.0)
    first.close()
    after = RawBrowser(viewer)  # the next browser gets the whole scene
    assert after.received_bytes(3.0) >= 0.9 * scene_bytes
    after.send(camera_message())
    forged = [
        (slider, {"value": float("nan")}),
        (slider, {"value": float("inf")}),
        (slider, {"value": True}),
        (slider, {"value": "x" * 1_000_000}),
        (slider, {"max": 1e308}),  # the page never sends a control's limits or label
        (slider, {"label": "x" * 100_000}),
        (slider, {}),
        (role, {"value": "x" * 1_000_000}),
        (role, {"options": ["x" * 1000] * 1000}),
    ]
    for uuid, updates in forged:
        after.send({"type": "GuiUpdateMessage", "uuid": uuid, "updates": updates})
    after.received_bytes(1.0)
    assert viewer.entry.t_s == TIMES_S[-1]
    assert viewer.slider.value == TIMES_S[-1]
    props = viewer.slider._impl.props
    assert (props.min, props.max, props.label) == (TIMES_S[0], TIMES_S[-1], "Case time (s)")
    assert viewer.role_menu.value == "surgeon"
    assert tuple(viewer.role_menu.options) == ("surgeon",)
    assert "Traceback" not in caplog.text
    assert "viewer: refused a control value" in caplog.text
    assert "viewer: clamped control 'Case time (s)'" in caplog.text
    after.send({"type": "GuiUpdateMessage", "uuid": slider, "updates": {"value": -1e308}})
    assert shows(viewer, TIMES_S[0])  # clamped to the first
    after.send({"type": "GuiUpdateMessage", "uuid": slider, "updates": {"value": TIMES_S[1]}})
    assert shows(viewer, TIMES_S[1])  # the page's own values still work
    after.close()


def read_line(proc: subprocess.Popen, timeout_s: float) -> str:
    """The first line the process prints, waited for at most ``timeout_s``."""
    found: list[str] = []
    reader = threading.Thread(target=lambda: found.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    assert found and found[0], f"egosurg view printed nothing within {timeout_s} s"
    return found[0]


def test_the_printed_url_carries_the_token_and_its_page_gets_the_case(case, tmp_path):
    from websockets.sync.client import connect

    proc = subprocess.Popen(
        [sys.executable, "-m", "protocol.cli", "view", str(case), "--port", "0",
         "--save-to", str(tmp_path / "v.toml")],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    try:
        line = read_line(proc, 120.0)
        # the first line: viser's own banner, an address without the token, is not shown
        assert line.startswith("egosurg view: "), line
        url = line.split(" at ", 1)[1].split()[0]
        parts = urllib.parse.urlsplit(url)
        (ws_url,) = urllib.parse.parse_qs(parts.query)["websocket"]
        token = urllib.parse.urlsplit(ws_url).path.strip("/")
        assert len(token) >= 32 and token in line
        with urllib.request.urlopen(url, timeout=10) as reply:  # the page, at the printed URL
            assert reply.status == 200 and b"<html" in reply.read().lower()
        origin = f"{parts.scheme}://{parts.netloc}"
        total = 0
        with connect(ws_url, origin=origin, max_size=None, open_timeout=10,
                     subprotocols=[f"viser-v{viser.__version__}"]) as ws:  # fmt: skip
            end = time.monotonic() + 3.0
            while (left := end - time.monotonic()) > 0:
                try:
                    total += len(ws.recv(timeout=left))
                except TimeoutError:
                    break
        assert total > SCENE_BYTES
    finally:
        proc.send_signal(signal.SIGINT)  # Ctrl-C, as the line says
        try:
            proc.wait(timeout=90)  # a loaded machine: the exit code is what counts
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 0  # Ctrl-C stops it cleanly


def test_a_viser_that_moved_the_checks_seams_does_not_start(tmp_path):
    """The check rests on two places inside viser (view_boundary's docstring); a viser whose
    upgrade moved either must not serve the case unchecked: the start stops with one line."""
    from viser import _messages

    from reconstructor.errors import ViewerError
    from reconstructor.replay.view_boundary import Boundary, BrowserGate

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        ws = server._websock_server
        gate = BrowserGate(Boundary.for_address("127.0.0.1", server.get_port()))
        live = ws._live_connections
        del ws._live_connections  # where the opening request is read
        with pytest.raises(ViewerError, match="pip install"):
            gate.install(server)
        ws._live_connections = live
        # viser's control handler no longer where the guard takes its place
        ws.unregister_handler(_messages.GuiUpdateMessage, server.gui._handle_gui_updates)
        with pytest.raises(ViewerError, match="pip install"):
            gate.install(server)
    finally:
        server.stop()


def test_a_wildcard_bind_still_needs_a_same_origin_page_and_the_token():
    """Bound to 0.0.0.0 (``--host``), the names the machine answers to are not known: the
    Origin must be the page at the Host the request names, and the token keeps others out."""
    from websockets.datastructures import Headers

    from reconstructor.replay.view_boundary import Boundary

    b = Boundary.for_address("0.0.0.0", 8080)
    ok = f"/{b.token}"

    def kind(path: str, host: str, origin: str) -> str | None:
        refused = b.refusal(path, Headers(Host=host, Origin=origin))
        return None if refused is None else refused[0]

    assert kind(ok, "workstation:8080", "http://workstation:8080") is None
    assert kind(ok, "10.0.0.5:8080", "http://10.0.0.5:8080") is None
    assert kind(ok, "workstation:8080", "http://evil.example") == "origin"
    assert kind("/", "workstation:8080", "http://workstation:8080") == "token"
    assert kind(f"/{b.token[:-1]}", "evil.example:8080", "http://evil.example:8080") == "token"
