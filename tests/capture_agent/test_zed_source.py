"""The ZED backend through a fake pyzed that behaves as ZED SDK 5.x (tests/fakes/pyzed): the
SDK's module replaced at its import, replaying PNG frames as the raw sensor images, with the
rectified views remapped through the factory calibration (the ``fake_sl`` fixture, conftest.py).
So a source that recorded the SDK's
rectified ``VIEW.LEFT`` / ``RIGHT`` instead of the raw ``*_UNRECTIFIED`` views fails here."""

from __future__ import annotations

import json
import logging
import queue
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from capture_agent.agent.agent import CameraWorker
from capture_agent.agent.ptp import PtpMonitor
from capture_agent.errors import CameraUnavailableError, SdkMissingError
from capture_agent.sources import CameraSource, GrabbedFrame, make_source
from capture_agent.sources.zed_source import ZedSource
from protocol.errors import ConfigError, UserError
from protocol.formats.camera_config import CameraConfig
from protocol.formats.node_config import NodeConfig
from protocol.formats.zed_conf import ZedFactoryCalibration
from protocol.toml_config import read_table

WHERE = "node.toml [[cameras]] #1"
SERIAL = 41234567
T0_NS = 1_767_225_600_008_000_000
PERIOD_NS = 33_333_333
# A ZED X factory file with real-looking distortion and a small stereo rotation, so the SDK's
# rectified views are visibly not the raw ones (SVGA derives from FHD1200, as on a ZED X).
CONF_TEXT = """[LEFT_CAM_FHD1200]
fx=1401.5
fy=1400.8
cx=962.3
cy=598.1
k1=-0.061
k2=0.028
p1=0.0009
p2=-0.0004
k3=-0.004

[RIGHT_CAM_FHD1200]
fx=1399.2
fy=1398.9
cx=951.7
cy=603.4
k1=-0.058
k2=0.025
p1=-0.0007
p2=0.0005
k3=-0.003

[STEREO]
Baseline=120.1
TY=0.35
TZ=-0.42
RX_FHD1200=0.0031
CV_FHD1200=-0.0052
RZ_FHD1200=0.0017
"""


def source_from_table(table: dict) -> CameraSource:
    return make_source(read_table(CameraConfig, {"source": "zed", **table}, WHERE))


def must(frame: GrabbedFrame | None) -> GrabbedFrame:
    assert frame is not None, "the camera timed out"
    return frame


def sensor_image(i: int, side: str) -> np.ndarray:
    """SVGA BGR with texture everywhere (a remap shows), a colour per side and frame (a BGR/RGB
    swap or a left/right mix-up shows)."""
    yy, xx = np.mgrid[0:600, 0:960]
    checker = (((yy // 24) + (xx // 24)) % 2).astype(np.uint8)
    base = np.array((200, 40 + 10 * i, 10) if side == "left" else (10, 40 + 10 * i, 200), np.uint8)
    img = (base[None, None, :] * (0.5 + 0.5 * checker[..., None])).astype(np.uint8)
    img[:100, :100] = (0, 0, 255)
    return img


def write_replay(directory: Path, events: list, **camera) -> dict[int, tuple[np.ndarray, ...]]:
    """PNG frames plus ``replay.json`` and the factory file the fake SDK "downloads". An event
    is a stamp (a frame), ``(stamp, warning)`` (a frame with an SDK 5 warning), an error or
    warning name (no image), or ``"wedge"`` (grab() hangs until close())."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"SN{SERIAL}.conf").write_text(CONF_TEXT)
    images: dict[int, tuple[np.ndarray, ...]] = {}
    out: list[dict] = []
    for i, event in enumerate(events):
        if event == "wedge":
            out.append({"wedge": True})
            continue
        if isinstance(event, str):
            out.append({"error": event})
            continue
        stamp, warning = event if isinstance(event, tuple) else (event, None)
        left, right = sensor_image(i, "left"), sensor_image(i, "right")
        cv2.imwrite(str(directory / f"l{i}.png"), left)
        cv2.imwrite(str(directory / f"r{i}.png"), right)
        item = {"timestamp_ns": stamp, "left": f"l{i}.png", "right": f"r{i}.png"}
        if warning:
            item["warning"] = warning
        out.append(item)
        images[stamp] = (left, right)
    replay = {"serial": SERIAL, "events": out, **camera}
    (directory / "replay.json").write_text(json.dumps(replay))
    return images


def zed_table(tmp_path: Path, **kw) -> dict:
    table = {"serial": SERIAL, "resolution": "SVGA", "fps": 30, "settings_dir": str(tmp_path)}
    table.update(kw)
    return table


def test_zed_records_the_raw_sensor_images_with_their_stamps(fake_sl, tmp_path):
    stamps = [T0_NS, T0_NS + PERIOD_NS, T0_NS + 3 * PERIOD_NS, T0_NS + 4 * PERIOD_NS]
    events = [stamps[0], stamps[1], stamps[2], "CORRUPTED_FRAME", stamps[3], "CAMERA_NOT_DETECTED"]
    images = write_replay(tmp_path / "replay", events)
    (tmp_path / f"SN{SERIAL}.conf").write_text(CONF_TEXT)
    src = source_from_table(zed_table(tmp_path))
    with src:
        assert src.serial == SERIAL and src.is_open
        before = time.time_ns()
        frames = [must(src.grab(2.0)) for _ in range(4)]
        # a frame the camera lost (between stamps 1 and 2) shows as an index gap
        assert [f.frame_index for f in frames] == [0, 1, 3, 4]
        assert [f.capture_unix_ns for f in frames] == stamps
        for f in frames:
            want_left, want_right = images[f.capture_unix_ns]
            assert f.left_bgr is not None and f.right_bgr is not None
            assert f.left_bgr.shape == (600, 960, 3) and f.left_bgr.dtype == np.uint8
            # the raw views (BGRA from the SDK -> BGR), not the SDK's rectified ones
            np.testing.assert_array_equal(f.left_bgr, want_left)
            np.testing.assert_array_equal(f.right_bgr, want_right)
            assert before - 10**9 <= f.host_receive_unix_ns <= time.time_ns()
        with pytest.raises(CameraUnavailableError, match="CAMERA_NOT_DETECTED"):
            src.grab(2.0)
        with pytest.raises(CameraUnavailableError):  # stays gone until reopened
            src.grab(0.1)
        src.close()
        src.open()  # the camera is back (the fake replays from its first frame)
        assert must(src.grab(2.0)).frame_index == 0
    assert isinstance(src, ZedSource) and src.corrupted_frames == 1
    assert src.grab_warnings == {"CORRUPTED_FRAME": 1}
    assert src.factory_conf_text() == CONF_TEXT


def test_the_fake_sdk_rectifies_through_the_factory_calibration(fake_sl, tmp_path):
    """The fake is only a good test if its rectified views differ from the raw ones, and differ
    as OpenCV's rectification with the file's model says."""
    write_replay(tmp_path / "replay", [T0_NS])
    sl = fake_sl
    init = sl.InitParameters()
    init.camera_resolution, init.camera_fps = sl.RESOLUTION.SVGA, 30
    init.optional_settings_path = str(tmp_path / "replay")
    cam = sl.Camera()
    assert cam.open(init) == sl.ERROR_CODE.SUCCESS
    try:
        assert cam.grab(sl.RuntimeParameters()) == sl.ERROR_CODE.SUCCESS
        views = {}
        for view in ("LEFT", "LEFT_UNRECTIFIED", "RIGHT", "RIGHT_UNRECTIFIED"):
            mat = sl.Mat()
            assert cam.retrieve_image(mat, getattr(sl.VIEW, view)) == sl.ERROR_CODE.SUCCESS
            views[view] = cv2.cvtColor(mat.get_data(), cv2.COLOR_BGRA2BGR)
    finally:
        cam.close()
    np.testing.assert_array_equal(views["LEFT_UNRECTIFIED"], sensor_image(0, "left"))
    for side in ("LEFT", "RIGHT"):
        diff = np.abs(views[side].astype(int) - views[f"{side}_UNRECTIFIED"].astype(int))
        assert diff.mean() > 5.0, side  # clearly another image, not a rounding difference
    # the left rectified view is the raw one remapped with the product's reading of the file
    st = ZedFactoryCalibration.parse(CONF_TEXT, serial=SERIAL).stereo("SVGA")
    size = (960, 600)
    R1, _, P1, *_ = cv2.stereoRectify(
        st.left.K, st.left.dist_array, st.right.K, st.right.dist_array, size,
        st.R_right_from_left, st.T_right_from_left_m * 1000.0, alpha=0,
    )  # fmt: skip
    mapx, mapy = cv2.initUndistortRectifyMap(
        st.left.K, st.left.dist_array, R1, P1, size, cv2.CV_32FC1
    )
    want = cv2.remap(sensor_image(0, "left"), mapx, mapy, cv2.INTER_LINEAR)
    assert np.abs(views["LEFT"].astype(int) - want.astype(int)).max() <= 1


def test_sdk_5_warnings_are_counted_and_logged_not_a_lost_camera(fake_sl, tmp_path, caplog):
    events = [
        (T0_NS, "POTENTIAL_CALIBRATION_ISSUE"),  # an image comes with it: recorded
        "CAMERA_REBOOTING",  # no new image: skipped
        (T0_NS + 2 * PERIOD_NS, "POTENTIAL_CALIBRATION_ISSUE"),
        T0_NS + 3 * PERIOD_NS,
    ]
    write_replay(tmp_path / "replay", events)
    src = source_from_table(zed_table(tmp_path))
    assert isinstance(src, ZedSource)
    with caplog.at_level(logging.WARNING, logger="capture_agent.sources.zed_source"), src:
        frames = [must(src.grab(2.0)) for _ in range(3)]
    assert [f.frame_index for f in frames] == [0, 2, 3]
    assert src.grab_warnings == {"POTENTIAL_CALIBRATION_ISSUE": 2, "CAMERA_REBOOTING": 1}
    assert src.corrupted_frames == 0
    logged = [r.getMessage() for r in caplog.records]
    # each warning logged once here (then at most every WARNING_LOG_INTERVAL_S), not per frame
    assert sum("POTENTIAL_CALIBRATION_ISSUE" in m for m in logged) == 1
    assert any("CAMERA_REBOOTING" in m and "skipped" in m for m in logged)


def test_an_sdk_older_than_5_is_refused_in_one_line(fake_sl, monkeypatch, tmp_path):
    monkeypatch.setattr(fake_sl, "SDK_VERSION", "4.2.5")
    with pytest.raises(SdkMissingError) as info:
        source_from_table(zed_table(tmp_path))
    message = str(info.value)
    assert "\n" not in message and isinstance(info.value, UserError)
    assert "ZED SDK 4.2.5 found" in message and ">= 5.0" in message
    assert "get_python_api.py" in message


def test_a_camera_opened_in_another_mode_is_refused_naming_both(fake_sl, tmp_path):
    # the camera runs SVGA only at 15 fps here: the SDK falls back and warns
    write_replay(tmp_path / "replay", [T0_NS], fps=15)
    src = source_from_table(zed_table(tmp_path))
    with pytest.raises(CameraUnavailableError) as info:
        src.open()
    assert "opened at 960x600 15 fps" in str(info.value)
    assert "configured SVGA (960x600) at 30 fps" in str(info.value)
    assert not src.is_open
    write_replay(tmp_path / "replay", [T0_NS], resolution="HD1080", fps=30)
    with pytest.raises(CameraUnavailableError, match=r"opened at 1920x1080 30 fps, not .*SVGA"):
        src.open()


def test_zed_grab_times_out_when_no_frame_comes(fake_sl, tmp_path):
    write_replay(tmp_path / "replay", [T0_NS])
    src = source_from_table(zed_table(tmp_path, settings_dir=str(tmp_path / "none")))
    src.open()
    try:
        assert src.grab(2.0) is not None
        t0 = time.monotonic()
        assert src.grab(0.2) is None
        assert 0.15 < time.monotonic() - t0 < 2.0
        assert src.factory_conf_text() == ""  # no SN<serial>.conf in settings_dir
    finally:
        t0 = time.monotonic()
        src.close()
        assert time.monotonic() - t0 < 3.0


def test_zed_open_failure_is_camera_unavailable(fake_sl, tmp_path):
    write_replay(tmp_path / "replay", [T0_NS])
    src = source_from_table(zed_table(tmp_path, serial=SERIAL + 1))
    with pytest.raises(CameraUnavailableError, match=rf"SN{SERIAL + 1}.*CAMERA_NOT_DETECTED"):
        src.open()
    assert not src.is_open


def test_a_wedged_sdk_close_does_not_hold_the_reopen(fake_sl, monkeypatch, tmp_path, caplog):
    """A wedged GMSL camera can hang in close() as it did in grab(): close() gives up after
    SDK_CLOSE_TIMEOUT_S, abandons that camera object, and the camera opens again."""
    write_replay(tmp_path / "replay", [T0_NS, "wedge"])
    monkeypatch.setattr("capture_agent.sources.zed_source.SDK_CLOSE_TIMEOUT_S", 0.2)
    release = threading.Event()
    sdk_close = fake_sl.Camera.close

    def hanging_close(cam):
        release.wait(10.0)
        sdk_close(cam)

    monkeypatch.setattr(fake_sl.Camera, "close", hanging_close)
    src = source_from_table(zed_table(tmp_path))
    try:
        src.open()
        assert must(src.grab(2.0)).frame_index == 0
        assert src.grab(0.3) is None  # wedged
        t0 = time.monotonic()
        with caplog.at_level(logging.ERROR, logger="capture_agent.sources.zed_source"):
            src.close()
        assert time.monotonic() - t0 < 3.0
        assert any("abandoning that camera object" in r.getMessage() for r in caplog.records)
        monkeypatch.setattr(fake_sl.Camera, "close", sdk_close)
        src.open()
        assert must(src.grab(2.0)).frame_index == 0
    finally:
        release.set()
        src.close()


def test_a_wedged_camera_is_reopened_by_the_agents_worker(fake_sl, tmp_path):
    """grab() hangs in the SDK (a GMSL camera that stopped): the worker sees no frame for
    ``watchdog_timeout_s``, closes the camera (the SDK's close releases the hung grab) and
    reopens it; frames flow again."""
    write_replay(tmp_path / "replay", [T0_NS, T0_NS + PERIOD_NS, "wedge"])
    node = NodeConfig.from_table(
        {
            "node_id": "orin-z",
            "frames_bind": "tcp://127.0.0.1:1",
            "control_bind": "tcp://127.0.0.1:2",
            "ptp": {"source": "none", "require_lock": False},
            "cameras": [{"source": "zed", **zed_table(tmp_path)}],
            "security": {"insecure": True},
            "watchdog_timeout_s": 0.5,
            "reopen_interval_s": 0.1,
        },
        "test node.toml",
    )
    out: queue.Queue = queue.Queue(maxsize=100)
    worker = CameraWorker(node.cameras[0], node, out, PtpMonitor(node.ptp))
    worker.start()
    try:
        deadline = time.monotonic() + 10.0
        indexes: list[int] = []
        while time.monotonic() < deadline and indexes.count(0) < 2:
            try:
                indexes.append(out.get(timeout=0.2).frame.frame_index)
            except queue.Empty:
                pass
    finally:
        worker.stop()
    assert indexes[:3] == [0, 1, 0], indexes  # two frames, the wedge, the reopen, frame 0
    status = worker.status(0)
    assert status.reopen_count >= 1


def test_zed_without_pyzed_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyzed", None)  # as on a machine without the ZED SDK
    monkeypatch.delitem(sys.modules, "pyzed.sl", raising=False)
    with pytest.raises(UserError) as info:
        source_from_table({"serial": SERIAL})
    message = str(info.value)
    assert "pyzed" in message and "ZED SDK" in message and "get_python_api.py" in message
    assert isinstance(info.value, ImportError)
    # a bad option is reported before the SDK is even needed
    with pytest.raises(ConfigError, match=r"fps = 120.*15, 30, 60"):
        source_from_table({"serial": SERIAL, "resolution": "HD1200", "fps": 120})
