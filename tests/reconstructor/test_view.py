"""``egosurg view``: a case served to the browser through viser (reconstructor/replay/view.py).

The case is written by hand (as bench/bench_replay.py's ``make_case`` does): two timestamps of a
wall of about 4,000 Gaussians, each painted with a different random pattern of coarse cells, in
front of a camera whose pose the test knows. What a user relies on:

- the page is served on 127.0.0.1 only, over HTTP, at an address that carries its token (who
  else is refused: test_view_boundary.py), and never offers a public share link;
- the splats handed to the browser are the case's model, checked against values computed here
  from the PLY file's bytes (not through the project's reader);
- the time slider switches the model; "Save viewpoint" writes a trajectory file our reader reads;
- bad input is one line and exit status 2 from the real ``egosurg view`` command;
- with Debian's ``chromium`` on PATH, the page opened in headless Chromium shows what the
  project's own renderer shows from the same camera (upright, not mirrored, not empty).
"""

from __future__ import annotations

import dataclasses
import math
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from protocol.formats.trajectory import (
    Keyframe,
    Trajectory,
    matrix_from_quat_wxyz,
    read_trajectories,
    write_trajectories,
)
from reconstructor.case.index import CaseIndex, Entry, checksum_file
from reconstructor.splats import ply
from reconstructor.splats.gaussians import Gaussians
from tests.browser import CHROMIUM_MISSING, SKIP_REASON, HeadlessChromium
from tests.helpers import REPO, run_egosurg

viser = pytest.importorskip("viser", reason="egosurg view needs viser: pip install -e '.[dev]'")

from reconstructor.replay.view import CaseViewer, ViewConfig  # noqa: E402

EYE_M = (0.3, -3.0, 1.1)
LOOK_AT_M = (0.0, 0.0, 1.0)
HFOV_DEG = 60.0
SIZE_PX = (640, 400)
TIMES_S = (2.0, 2.5)


def wall(seed: int) -> Gaussians:
    """A 4 m x 2.6 m wall at y = 0 of Gaussians 5 cm apart, painted with 6 x 4 random cells
    (so a flipped or mirrored view of it does not correlate with the upright one)."""
    rng = np.random.default_rng(seed)
    x, z = np.meshgrid(np.arange(-2.0, 2.0, 0.05), np.arange(-0.3, 2.3, 0.05), indexing="ij")
    x, z = x.ravel(), z.ravel()
    n = x.size
    cells = rng.uniform(0.05, 0.95, size=(6, 4, 3))
    cx = np.clip(((x + 2.0) / 4.0 * 6).astype(int), 0, 5)
    cz = np.clip(((z + 0.3) / 2.6 * 4).astype(int), 0, 3)
    colour = cells[cx, cz]
    angle = rng.uniform(0, math.pi, n)  # flat discs turned about y: covariances off the axes
    quat = np.stack([np.cos(angle / 2), 0 * angle, np.sin(angle / 2), 0 * angle], axis=1)
    scales = np.stack([np.full(n, 0.035), np.full(n, 0.004), np.full(n, 0.02)], axis=1)
    c0 = 1.0 / (2.0 * math.sqrt(math.pi))
    return Gaussians(
        means_m=torch.tensor(np.stack([x, rng.normal(0, 0.002, n), z], 1), dtype=torch.float32),
        quats_wxyz=torch.tensor(quat, dtype=torch.float32),
        log_scales=torch.tensor(np.log(scales), dtype=torch.float32),
        opacity_logits=torch.full((n,), 4.0),
        sh_dc=torch.tensor((colour - 0.5) / c0, dtype=torch.float32),
        sh_rest=torch.zeros(n, 0, 3),
    )


def make_case(folder: Path, times_s: tuple[float, ...] = TIMES_S) -> Path:
    """A hand-made case of ``wall`` models, one done timestamp at each of ``times_s``."""
    (folder / "models").mkdir(parents=True)
    entries = []
    for k, t in enumerate(times_s):
        name = f"t{t:09.3f}"
        path = ply.write_ply(folder / "models" / f"{name}.ply", wall(seed=k), unit_quats=True)
        digest, size = checksum_file(path)
        entries.append(Entry(
            name=name, t_s=t, set_index=k, model=f"models/{name}.ply", xxh3_64=digest,
            bytes=size, status="done", gaussians=wall(seed=k).num,
        ))  # fmt: skip
    CaseIndex(
        session="hand-made", session_started_unix_ns=0, config_hash="test", warm_start=False,
        created_unix_ns=time.time_ns(), timestamps=tuple(entries),
    ).write(folder)  # fmt: skip
    return folder


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    return make_case(tmp_path_factory.mktemp("view") / "case")


def start_keyframe() -> Keyframe:
    return Keyframe(time_s=TIMES_S[0], eye_m=EYE_M, look_at_m=LOOK_AT_M, fov_deg=HFOV_DEG)


@pytest.fixture()
def viewer(case, tmp_path):
    config = ViewConfig(
        port=0, save_to=tmp_path / "viewpoints.toml", start=start_keyframe(),
        start_aspect=SIZE_PX[0] / SIZE_PX[1],
    )  # fmt: skip
    v = CaseViewer(case, config)
    yield v
    v.close()


def read_ply_bytes(path: Path) -> dict[str, np.ndarray]:
    """The PLY's vertex table, parsed here from its header and bytes."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    names = [
        line.split()[2]
        for line in data[:end].decode().splitlines()
        if line.startswith("property float")
    ]
    table = np.frombuffer(data[end:], dtype=np.dtype([(n, "<f4") for n in names]))
    return {n: table[n].astype(np.float64) for n in names}


def expected_splats(path: Path):
    """Centres, covariances R S S Rᵀ, colours and opacities of a PLY, by scipy's rotation."""
    from scipy.spatial.transform import Rotation

    v = read_ply_bytes(path)
    centres = np.stack([v["x"], v["y"], v["z"]], 1)
    quat_xyzw = np.stack([v["rot_1"], v["rot_2"], v["rot_3"], v["rot_0"]], 1)
    R = Rotation.from_quat(quat_xyzw).as_matrix()
    S = np.exp(np.stack([v["scale_0"], v["scale_1"], v["scale_2"]], 1))
    cov = R @ (S[:, :, None] ** 2 * np.swapaxes(R, 1, 2))
    c0 = 0.28209479177387814
    rgb = np.clip(0.5 + c0 * np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], 1), 0, 1)
    opacity = 1 / (1 + np.exp(-v["opacity"]))
    return centres, cov, rgb, opacity


def decode_viser_buffer(handle) -> tuple[np.ndarray, ...]:
    """What the browser receives: viser's per-Gaussian 32 bytes (centre float32 x 3, a free
    word, the covariance's upper triangle float16 x 6, RGBA bytes), scaled by the node."""
    buf = np.ascontiguousarray(handle.buffer)
    scale = float(handle.scale)
    centres = buf[:, 0:3].view(np.float32).astype(np.float64) * scale
    triu = buf[:, 4:7].view(np.float16).astype(np.float64) * scale**2
    cov = np.empty((len(buf), 3, 3))
    for k, (i, j) in enumerate([(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]):
        cov[:, i, j] = cov[:, j, i] = triu[:, k]
    rgba = buf[:, 7:8].view(np.uint8).astype(np.float64) / 255.0
    return centres, cov, rgba[:, :3], rgba[:, 3]


def listening_addresses(port: int) -> set[str]:
    """Local addresses with a TCP socket listening on ``port`` (Linux's /proc/net/tcp*)."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            addr, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                if len(addr) == 8:
                    found.add(socket.inet_ntoa(bytes.fromhex(addr)[::-1]))
                else:
                    found.add(addr)
    return found


def test_serves_the_page_on_loopback_only(viewer):
    port = viewer.server.get_port()
    # the page's address carries the websocket's, with the viewer's token (test_view_boundary.py)
    assert viewer.url.startswith(f"http://127.0.0.1:{port}/?websocket=ws://127.0.0.1:{port}/")
    with urllib.request.urlopen(viewer.url, timeout=10) as reply:
        assert reply.status == 200
        assert b"<html" in reply.read().lower()
    if Path("/proc/net/tcp").exists():
        assert listening_addresses(port) == {"127.0.0.1"}
    # viser's share button would tunnel the case through a public relay: refused
    assert viewer.server.request_share_url() is None


def test_splats_handed_to_the_browser_are_the_models(viewer, case):
    for t in TIMES_S:
        viewer.slider.value = t  # what the page's slider does: case time
        assert viewer.entry.t_s == t
        centres, cov, rgb, opacity = expected_splats(case / "models" / f"t{t:09.3f}.ply")
        got_centres, got_cov, got_rgb, got_opacity = decode_viser_buffer(viewer.splats)
        np.testing.assert_allclose(got_centres, centres, atol=1e-6)
        # float16 keeps 11 significant bits: 1e-3 relative to the Gaussian's largest variance
        largest = np.abs(cov).max(axis=(1, 2))[:, None, None]
        assert np.abs(got_cov - cov).max() <= 1e-3 * largest.max()
        assert np.all(np.abs(got_cov - cov) <= 1e-3 * largest + 1e-9)
        np.testing.assert_allclose(got_rgb, rgb, atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(got_opacity, opacity, atol=0.5 / 255 + 1e-6)
    # the two timestamps are different paintings: the slider did switch the model
    assert not np.allclose(expected_splats(case / "models" / f"t{TIMES_S[0]:09.3f}.ply")[2], rgb)


def test_saved_viewpoint_reads_back_as_a_trajectory(viewer, tmp_path):
    viewer.slider.value = TIMES_S[1]
    pose = start_keyframe().pose()
    viewer.save(Keyframe.from_pose(viewer.entry.t_s, pose, HFOV_DEG))
    viewer.slider.value = TIMES_S[0]
    viewer.save(Keyframe.from_pose(viewer.entry.t_s, pose, 45.0))
    (saved,) = read_trajectories(tmp_path / "viewpoints.toml")
    assert saved.name == "viewer"
    assert [k.time_s for k in saved.keyframes] == list(TIMES_S)
    assert [k.fov_deg for k in saved.keyframes] == [45.0, HFOV_DEG]
    back = saved.keyframes[1].pose()
    np.testing.assert_allclose(back.R, pose.R, atol=1e-5)
    np.testing.assert_allclose(back.centre_m, EYE_M, atol=1e-5)


def websocket_url(viewer) -> str:
    """The websocket address the page connects to: the printed URL's ``websocket`` parameter
    (viser's page takes its server from it), which carries the viewer's token."""
    query = urllib.parse.parse_qs(urllib.parse.urlsplit(viewer.url).query)
    return query["websocket"][0]


OWN_ORIGIN = "the viewer's own"


class RawBrowser:
    """A websocket client that speaks viser's handshake and then sends what it likes: the
    hostile (or broken) browser the viewer must survive. By default it is the viewer's own page
    (its origin, its host, the token); ``url``, ``origin`` (None: no Origin header) and ``host``
    (the Host header, as a DNS-rebinding page would send it) make it another."""

    def __init__(
        self, viewer, *, url: str | None = None, origin: str | None = OWN_ORIGIN,
        host: str | None = None,
    ) -> None:  # fmt: skip
        from websockets.sync.client import connect

        port = viewer.server.get_port()
        parts = urllib.parse.urlsplit(url or websocket_url(viewer))
        if host is not None:
            parts = parts._replace(netloc=host)
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.ws = connect(
            urllib.parse.urlunsplit(parts), sock=sock, max_size=None, open_timeout=10,
            origin=f"http://127.0.0.1:{port}" if origin == OWN_ORIGIN else origin,
            subprotocols=[f"viser-v{viser.__version__}"],
        )  # fmt: skip

    def received_bytes(self, seconds: float) -> int:
        """Bytes the server sent in ``seconds``; stops early when it closes the connection."""
        from websockets.exceptions import ConnectionClosed

        total, end = 0, time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                total += len(self.ws.recv(timeout=left))
            except (TimeoutError, ConnectionClosed):
                break
        return total

    def closed_by_server(self, seconds: float = 10.0) -> bool:
        from websockets.exceptions import ConnectionClosed

        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                self.ws.recv(timeout=left)
            except ConnectionClosed:
                return True
            except TimeoutError:
                return False
        return False

    def send(self, message: dict) -> None:
        import msgspec

        self.ws.send(msgspec.msgpack.encode(message))

    def close(self) -> None:
        self.ws.close()


def gui_uuid(viewer, label: str) -> str:
    """The id the page uses for a control (the page learns it from the GUI messages)."""
    handles = viewer.server.gui._gui_input_handle_from_uuid  # viser keeps no public index
    return next(u for u, h in handles.items() if h._impl.props.label == label)


def test_a_hostile_browser_is_dropped_and_the_viewer_goes_on(viewer, tmp_path, caplog):
    """The viewer's own page, broken or taken over, can send anything: unreadable messages lose
    their own connection (one warning line each, no traceback), forged controls cannot break
    the shown case or write a bad viewpoint, and the next browser gets the whole scene."""
    import msgspec

    caplog.set_level("INFO")
    first = RawBrowser(viewer)
    scene_bytes = first.received_bytes(3.0)
    first.close()
    assert scene_bytes > 100_000  # the wall's splats: 4,000 x 32 bytes
    junk = [
        b"\x00" * 10,
        np.random.default_rng(0).bytes(4096),
        b"\x81" * (5 << 20),  # nested maps: deep recursion in the decoder
        msgspec.msgpack.encode({"type": "NoSuchMessage"}),
        msgspec.msgpack.encode([1, 2, 3]),
        msgspec.msgpack.encode({"type": "ViewerCameraMessage", "wxyz": "x"}),
        msgspec.msgpack.encode({"type": "GuiUpdateMessage", "updates": {}}),
    ]
    for payload in junk:
        browser = RawBrowser(viewer)
        browser.ws.send(payload)
        assert browser.closed_by_server(), payload[:20]
    assert caplog.text.count("closed a browser connection whose message") == len(junk)

    def camera(wxyz, position) -> dict:
        return {"type": "ViewerCameraMessage", "wxyz": wxyz, "position": position, "fov": 0.9,
                "near": 0.01, "far": 100.0, "image_height": 400, "image_width": 640,
                "look_at": (0.0, 0.0, 1.0), "up_direction": (0.0, 0.0, 1.0)}  # fmt: skip

    forged = RawBrowser(viewer)
    forged.received_bytes(1.0)
    forged.send(camera((1.0, 0.0, 0.0, 0.0), (0.0, -3.0, 1.0)))  # viser counts it in now
    slider = gui_uuid(viewer, "Case time (s)")
    forged.send({"type": "GuiUpdateMessage", "uuid": slider, "updates": {"value": 10**9}})
    forged.send(camera((0.0, 0.0, 0.0, 0.0), (float("nan"), 0.0, 1.0)))
    forged.send({"type": "GuiUpdateMessage", "uuid": gui_uuid(viewer, "Save viewpoint"),
                 "updates": {"value": True}})  # fmt: skip
    deadline = time.monotonic() + 10
    while "not saved" not in caplog.text and time.monotonic() < deadline:
        time.sleep(0.05)
    forged.close()
    assert "not saved: the browser's camera is not a valid view" in caplog.text
    assert not (tmp_path / "viewpoints.toml").exists()  # nothing half-written
    assert viewer.entry.t_s == TIMES_S[-1]  # a slider forged past the end shows the last
    assert "Traceback" not in caplog.text

    after = RawBrowser(viewer)
    assert after.received_bytes(3.0) >= 0.9 * scene_bytes
    after.close()
    with urllib.request.urlopen(viewer.url, timeout=10) as reply:
        assert reply.status == 200


def one_line_error(result) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    return lines[0]


def test_bad_input_is_one_line_and_exit_2(case, tmp_path):
    line = one_line_error(run_egosurg("view", str(tmp_path), timeout=60))
    assert "not a case folder" in line
    pending = make_case(tmp_path / "pending")
    index = CaseIndex.read(pending)
    undone = tuple(Entry(name=e.name, t_s=e.t_s, set_index=e.set_index) for e in index.timestamps)
    dataclasses.replace(index, timestamps=undone).write(pending)
    assert "no finished timestamp" in one_line_error(run_egosurg("view", str(pending)))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = one_line_error(run_egosurg("view", str(case), "--port", str(port)))
        assert f"port {port}" in line and "in use" in line
    no_viser = (
        "import sys; sys.modules['viser'] = None; from protocol.cli import main; "
        f"sys.exit(main(['view', {str(case)!r}, '--port', '0']))"
    )
    result = subprocess.run(
        [sys.executable, "-c", no_viser], capture_output=True, text=True, timeout=60, cwd=REPO
    )
    assert "pip install 'egosurg[view]'" in one_line_error(result)


def test_role_cameras_and_site_boxes_are_drawn(case, tmp_path):
    from protocol.formats.site import SiteBox, site_toml

    roles = tmp_path / "roles.toml"
    write_trajectories(roles, [Trajectory(name="surgeon", keyframes=(
        Keyframe(time_s=TIMES_S[0], eye_m=(0.5, -1.5, 1.7), look_at_m=(0.0, 0.0, 1.0)),
        Keyframe(time_s=TIMES_S[1], eye_m=(-0.5, -1.5, 1.6), look_at_m=(0.0, 0.0, 1.0)),
    ))])  # fmt: skip
    site = tmp_path / "site.toml"
    monitor = SiteBox(name="monitor-a", centre_m=(1.0, -1.0, 1.5), size_m=(0.01, 0.6, 0.4),
                      yaw_deg=90.0)  # fmt: skip
    site.write_text(site_toml([monitor]))
    config = ViewConfig(port=0, roles=roles, sites=(site,), save_to=tmp_path / "v.toml")
    with CaseViewer(case, config) as v:
        for k, eye in enumerate([(0.5, -1.5, 1.7), (-0.5, -1.5, 1.6)]):
            v.slider.value = TIMES_S[k]  # the surgeon's frustum follows the shown time
            frustum = v.frustums["surgeon"]
            np.testing.assert_allclose(frustum.position, eye, atol=1e-6)
            forward = matrix_from_quat_wxyz(frustum.wxyz)[:, 2]  # OpenCV: +z looks
            want = np.subtract((0.0, 0.0, 1.0), eye)
            np.testing.assert_allclose(forward, want / np.linalg.norm(want), atol=1e-6)
        box = v.box_nodes["monitor-a"]
        np.testing.assert_allclose(box.position, monitor.centre_m)
        np.testing.assert_allclose(box.dimensions, monitor.size_m)
        # the box's x axis turned 90 degrees about +z: along world +y
        np.testing.assert_allclose(matrix_from_quat_wxyz(box.wxyz)[:, 0], (0, 1, 0), atol=1e-9)


def test_a_role_camera_where_nobody_followed_the_person_says_so(case, tmp_path):
    """Inside a gap of a role's trajectory (hidden from every camera, or between two tracks
    joined as one role), and past its last keyframe, the camera is grey and labelled: the path's
    guess there is nobody's eye."""
    from reconstructor.replay.view import NOT_FOLLOWED_COLOUR, ROLE_COLOUR

    look = (0.0, 0.0, 1.0)
    roles = tmp_path / "roles.toml"
    write_trajectories(roles, [
        Trajectory(name="surgeon", keyframes=(
            Keyframe(time_s=2.0, eye_m=(0.5, -1.5, 1.7), look_at_m=look),
            Keyframe(time_s=2.2, eye_m=(0.4, -1.5, 1.7), look_at_m=look),
            Keyframe(time_s=2.8, eye_m=(0.0, -1.5, 1.7), look_at_m=look),
        ), gaps_s=((2.2, 2.8),)),
        Trajectory(name="anaesthetist", keyframes=(
            Keyframe(time_s=1.5, eye_m=(-1.5, 0.0, 1.6), look_at_m=look),
            Keyframe(time_s=2.2, eye_m=(-1.5, 0.1, 1.6), look_at_m=look),
        )),
    ])  # fmt: skip
    config = ViewConfig(port=0, roles=roles, save_to=tmp_path / "v.toml")
    with CaseViewer(case, config) as v:
        v.slider.value = TIMES_S[0]
        for name in ("surgeon", "anaesthetist"):
            assert v.labels[name].text == name
            assert tuple(v.frustums[name].color) == ROLE_COLOUR
        v.slider.value = TIMES_S[1]  # 2.5 s: inside the surgeon's gap, after the other's end
        assert v.labels["surgeon"].text == "surgeon (not followed 2.2-2.8 s)"
        assert v.labels["anaesthetist"].text == "anaesthetist (followed 1.5-2.2 s only)"
        for name in ("surgeon", "anaesthetist"):
            assert tuple(v.frustums[name].color) == NOT_FOLLOWED_COLOUR


def grey_band(rgb: np.ndarray) -> np.ndarray:
    """The lower 60 % of an RGB image (above it the page shows its panel and a notice), grey,
    downsampled to 64 x 24: compares layout and shading, not pixels."""
    import cv2

    g = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float64)
    return cv2.resize(g[int(0.4 * g.shape[0]) :], (64, 24), interpolation=cv2.INTER_AREA)


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


@pytest.mark.skipif(CHROMIUM_MISSING, reason=SKIP_REASON)
def test_browser_shows_what_our_renderer_shows(viewer, case, tmp_path):
    import cv2

    from protocol.camera import Camera, Intrinsics
    from reconstructor.replay.run import case_raster, render_view

    g = viewer.models.load(viewer.models.entries[0])
    camera = Camera(name="start", intrinsics=Intrinsics.from_fov(*SIZE_PX, HFOV_DEG),
                    pose=start_keyframe().pose())  # fmt: skip
    ours = grey_band(render_view(g, camera, case_raster(case))[0])
    assert correlation(ours, ours[::-1]) < 0.5 and correlation(ours, ours[:, ::-1]) < 0.5
    keep = Path(tempfile.gettempdir()) / "egosurg_test_view_page.png"
    browser = HeadlessChromium(tmp_path / "profile", size_px=SIZE_PX)
    try:
        # the page's size exactly (a headless window's viewport is smaller than the window)
        browser.call("Emulation.setDeviceMetricsOverride", width=SIZE_PX[0], height=SIZE_PX[1],
                     deviceScaleFactor=1, mobile=False)  # fmt: skip
        browser.call("Page.navigate", url=viewer.url)
        # wait for the splats: they arrive, then fade in; 45 s bounds a loaded machine
        deadline, best = time.monotonic() + 45, -1.0
        while time.monotonic() < deadline and best <= 0.8:
            time.sleep(0.5)
            shot = browser.screenshot()
            best = correlation(grey_band(shot), ours)
        # "Save viewpoint" with the browser's own camera, as its button does
        clients = list(viewer.server.get_clients().values())
        assert clients, "the page never connected to the viewer"
        viewer.save_from_client(clients[0])
    finally:
        browser.close()
    cv2.imwrite(str(keep), np.ascontiguousarray(shot[:, :, ::-1]))
    page = grey_band(shot)
    assert page.std() > 10, f"the page shows no splats (screenshot: {keep})"
    assert correlation(page, ours) > 0.8, f"the page differs from our render ({keep})"
    (back,) = read_trajectories(viewer.config.save_to)
    key = back.keyframes[0]
    np.testing.assert_allclose(key.pose().R, start_keyframe().pose().R, atol=1e-3)
    np.testing.assert_allclose(key.eye_m, EYE_M, atol=1e-3)
    assert key.fov_deg == pytest.approx(HFOV_DEG, abs=0.1)


# ---- which session: the viewer checks its files, and saves the case's ----------------------

CASE_START_NS = 1_767_225_600_000_000_000  # 2026-01-01 00:00:00 UTC
OTHER_START_NS = 1_795_856_400_000_000_000  # 2026-11-28 09:00:00 UTC: another recording


def session_case(folder: Path) -> Path:
    """The hand-made case, as one reconstructed from a session that started at
    ``CASE_START_NS`` (its session file gone: the start is the whole check)."""
    make_case(folder)
    index = CaseIndex.read(folder)
    dataclasses.replace(index, session=str(folder / "gone.h5"),
                        session_started_unix_ns=CASE_START_NS).write(folder)  # fmt: skip
    return folder


def test_files_of_another_session_are_refused_in_one_line_and_saved_viewpoints_name_it(tmp_path):
    """Today the viewer drew another session's roles and boxes without a word (a role's eye
    where nobody stood in this case) and saved viewpoints that named no session."""
    from protocol.formats.session_id import SessionId, SessionMismatchError
    from protocol.formats.site import SiteBox, site_toml
    from protocol.formats.trajectory import read_trajectory_file

    case = session_case(tmp_path / "case")
    other = SessionId(name="demo-or1", started_unix_ns=OTHER_START_NS)
    roles = tmp_path / "demo_roles.toml"
    write_trajectories(roles, [Trajectory(name="surgeon", keyframes=(start_keyframe(),))],
                       session=other)  # fmt: skip
    box = SiteBox(name="drape", centre_m=(0.0, 0.0, 0.8), size_m=(1.0, 0.6, 0.3))
    site = tmp_path / "demo_site.toml"
    site.write_text(site_toml([box], session=other))
    line = one_line_error(run_egosurg("view", str(case), "--roles", str(roles), "--port", "0",
                                      "--save-to", str(tmp_path / "v.toml")))  # fmt: skip
    assert "demo_roles.toml was made for session 'demo-or1' started 2026-11-28 09:00:00" in line
    assert "but the case" in line and "started 2026-01-01 00:00:00.000 UTC" in line
    for config in (ViewConfig(port=0, sites=(site,), save_to=tmp_path / "v.toml"),
                   ViewConfig(port=0, fields=(site,), save_to=tmp_path / "v.toml"),
                   ViewConfig(port=0, save_to=roles)):  # fmt: skip
        with pytest.raises(SessionMismatchError, match="was made for session 'demo-or1'"):
            CaseViewer(case, config)
    ours = tmp_path / "roles.toml"
    mine = SessionId(name="", started_unix_ns=CASE_START_NS)
    write_trajectories(ours, [Trajectory(name="surgeon", keyframes=(start_keyframe(),))],
                       session=mine)  # fmt: skip
    config = ViewConfig(port=0, roles=ours, save_to=tmp_path / "v.toml", timezone="UTC")
    with CaseViewer(case, config) as v:
        v.slider.value = TIMES_S[1]
        v.save(Keyframe.from_pose(v.entry.t_s, start_keyframe().pose(), HFOV_DEG))
        # the panel reads the shown time as case time and as the time of day
        assert "**2.500 s** of the case · **00:00:02.500 UTC** on 2026-01-01" in v.time_text.content
    saved = read_trajectory_file(tmp_path / "v.toml")
    assert saved.session is not None and saved.session.started_unix_ns == CASE_START_NS


def test_the_time_slider_is_in_case_time(viewer):
    """Seconds of case time, from the first done timestamp to the last, marked at both ends;
    a time between two timestamps shows the nearer."""
    props = viewer.slider._impl.props
    assert (props.min, props.max, props.label) == (TIMES_S[0], TIMES_S[1], "Case time (s)")
    assert [m.value for m in props._marks] == list(TIMES_S)
    viewer.slider.value = 2.4
    assert viewer.entry.t_s == TIMES_S[1] and viewer.slider.value == TIMES_S[1]
    viewer.slider.value = 2.2
    assert viewer.entry.t_s == TIMES_S[0]
