"""Camera sources: the sim backend against its own truth and the video backend on real video files
written here (the ZED backend is test_zed_source.py's). Timing assertions leave generous slack."""

from __future__ import annotations

import itertools
import math
import re
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from capture_agent.errors import CameraUnavailableError, EndOfRecordingError
from capture_agent.sources import CameraSource, GrabbedFrame, make_source
from capture_agent.sources.sim_source import DAY_NS, SimSource
from protocol.camera import Resolution
from protocol.errors import ConfigError
from protocol.formats.camera_config import CameraConfig, FaultSpec, SimSourceConfig
from protocol.formats.zed_conf import ZedFactoryCalibration
from protocol.images import decode_image
from protocol.toml_config import read_table
from tests.helpers import heavy_modules_after

WHERE = "node.toml [[cameras]] #1"
# One epoch for every sim source here, as every agent of a rig shares one; an hour ago keeps
# sim times small.
EPOCH = (time.time_ns() - 3600 * 10**9) // 10**9 * 10**9


def source_from_table(kind: str, table: dict, where: str) -> CameraSource:
    """The source of a node.toml ``[[cameras]]`` table with ``source = kind``."""
    return make_source(read_table(CameraConfig, {"source": kind, **table}, where))


def sim(world, **kw) -> SimSource:
    kw.setdefault("epoch_unix_ns", EPOCH)
    return SimSource(SimSourceConfig(seed=11, **kw), world=world)


def must(frame: GrabbedFrame | None) -> GrabbedFrame:
    assert frame is not None, "the camera timed out"
    return frame


def left(frame: GrabbedFrame) -> np.ndarray:
    assert frame.left_bgr is not None
    return frame.left_bgr


def right(frame: GrabbedFrame) -> np.ndarray:
    assert frame.right_bgr is not None
    return frame.right_bgr


def grab_for(src: CameraSource, seconds: float, timeout_s: float = 1.0) -> list[GrabbedFrame]:
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out.append(must(src.grab(timeout_s)))
    return out


# ---- sim ---------------------------------------------------------------------------------------
def test_sim_frames_follow_the_camera_clock_in_real_time(world):
    src = sim(world, camera_index=0, drop_probability=0.2)
    with src:
        t0 = time.monotonic()
        frames = grab_for(src, 1.5)
        elapsed = time.monotonic() - t0
    assert not src.is_open
    # real time at the configured fps, minus the camera's drops
    expected = 30 * 0.8 * elapsed
    assert 0.6 * expected < len(frames) < 1.3 * expected + 3
    span_s = (frames[-1].capture_unix_ns - frames[0].capture_unix_ns) / 1e9
    assert abs(span_s - elapsed) < 0.6
    # grab() waited for each frame's stamp: none arrives before the camera stamped it
    assert all(f.host_receive_unix_ns >= f.capture_unix_ns - 5_000_000 for f in frames)
    assert abs(frames[-1].host_receive_unix_ns - time.time_ns()) < 2e9

    truth = src.truth(frames[0].capture_unix_ns - 10**9, frames[-1].capture_unix_ns + 10**9)
    stamp = dict(zip(truth.frame_index.tolist(), truth.capture_unix_ns.tolist(), strict=True))
    dropped = dict(zip(truth.frame_index.tolist(), truth.dropped.tolist(), strict=True))
    indices = [f.frame_index for f in frames]
    # the index jumps exactly over the frames the camera dropped, and nowhere else
    for a, b in itertools.pairwise(indices):
        assert b - a - 1 == sum(dropped[i] for i in range(a + 1, b)), (a, b)
        assert all(dropped[i] for i in range(a + 1, b))
    assert sum(dropped[i] for i in range(indices[0], indices[-1])) > 0
    assert src.overrun_frames == 0 and src.fault_frames == 0
    assert [f.capture_unix_ns for f in frames] == [stamp[i] for i in indices]
    # one frame period per index step: 30 fps within the crystal's ppm
    per_frame_s = span_s / (indices[-1] - indices[0])
    assert per_frame_s == pytest.approx(1 / 30, rel=1e-3)
    for f in frames[:3]:
        assert f.left_bgr is not None and f.right_bgr is not None and f.encoded is None
        assert f.left_bgr.shape == (600, 960, 3) and f.left_bgr.dtype == np.uint8
        assert f.right_bgr.shape == (600, 960, 3)


def test_sim_images_are_the_world_render_in_bgr(world):
    src = sim(world, camera_index=1, resolution="SVGA", realtime=False, content_fps=0.5)
    with src:
        frame = src.grab(0.0)
    assert frame is not None and frame.left_bgr is not None and frame.right_bgr is not None
    exposure = src.clock.exposure_time(frame.frame_index)
    content_t = math.floor(exposure * 0.5) / 0.5
    left, right = world.render_stereo(1, content_t, "SVGA")
    np.testing.assert_array_equal(frame.left_bgr, left.image_rgb[..., ::-1])
    np.testing.assert_array_equal(frame.right_bgr, right.image_rgb[..., ::-1])
    assert not frame.left_bgr.flags.writeable  # shared between frames


def test_two_cameras_of_one_world_have_their_own_phase(world):
    # content does not matter here: render less. No stamp jitter: the phase is the clock's, and
    # 150 us of jitter per stamp, on whichever frames a loaded machine happens to grab, can
    # bring one pair of stamps within 0.1 ms of each other
    a = sim(world, camera_index=0, content_fps=0.5, jitter_ns_std=0.0)
    b = sim(world, camera_index=2, content_fps=0.5, jitter_ns_std=0.0)
    assert a.serial != b.serial
    assert {a.serial, b.serial} <= {u.serial for u in world.rig}
    period = 1 / 30
    diff = abs(a.clock.exposure_time(0) - b.clock.exposure_time(0)) % period
    assert min(diff, period - diff) > 2e-4
    with a, b:
        fa, fb = [], []
        for _ in range(8):
            fa.append(must(a.grab(1.0)))
            fb.append(must(b.grab(1.0)))
    # the two streams are offset by their phase difference, not aligned
    offsets_ms = [
        ((x.capture_unix_ns - y.capture_unix_ns) / 1e6) % (1000 / 30)
        for x in fa
        for y in fb
        if x.frame_index == fa[0].frame_index
    ]
    assert all(min(o, 1000 / 30 - o) > 0.1 for o in offsets_ms)
    ta = a.truth(fa[0].capture_unix_ns - 10**9, fa[-1].capture_unix_ns + 10**9)
    tb = b.truth(fa[0].capture_unix_ns - 10**9, fa[-1].capture_unix_ns + 10**9)
    assert not set(ta.capture_unix_ns.tolist()) & set(tb.capture_unix_ns.tolist())


def test_sim_hang_times_out_for_its_duration_then_frames_resume(world):
    hang = FaultSpec(kind="hang", at_s=0.6, duration_s=1.0)
    src = sim(world, camera_index=3, content_fps=0.5, faults=(hang,))
    events = []
    with src:
        (kind, start, end) = src.fault_windows_unix_ns()[0]
        assert kind == "hang"
        stop = time.monotonic() + 2.4
        while time.monotonic() < stop:
            frame = src.grab(0.2)
            events.append((time.time_ns(), frame))  # when grab() returned
    pattern = "".join("f" if f is not None else "." for _, f in events)
    assert re.fullmatch(r"f+\.+f+", pattern), pattern
    timeouts = [t for t, f in events if f is None]
    assert (timeouts[-1] - timeouts[0]) / 1e9 == pytest.approx(1.0 - 0.2, abs=0.45)
    assert start <= timeouts[0] and timeouts[-1] <= end + 0.3e9
    frames = [f for _, f in events if f is not None]
    assert not any(start <= f.capture_unix_ns < end for f in frames)
    before = [f for f in frames if f.capture_unix_ns < start]
    after = [f for f in frames if f.capture_unix_ns >= end]
    assert before and after
    assert after[0].frame_index - before[-1].frame_index >= 0.8 * 30 * 1.0
    assert src.fault_frames >= 25


def test_sim_vanish_raises_until_it_is_over_then_reopen_works(world):
    vanish = FaultSpec(kind="vanish", at_s=0.5, duration_s=1.0)
    src = sim(world, camera_index=2, content_fps=0.5, faults=(vanish,))
    src.open()
    try:
        _, start, end = src.fault_windows_unix_ns()[0]
        last = None
        with pytest.raises(CameraUnavailableError, match="vanished"):
            for _ in range(200):
                last = src.grab(1.0)
        raised_at = time.time_ns()
        assert last is not None
        assert start <= raised_at < start + 0.5e9
        with pytest.raises(CameraUnavailableError):  # gone until reopened
            src.grab(0.1)
        src.close()
        with pytest.raises(CameraUnavailableError, match="not connected"):
            src.open()
        time.sleep(max(0.0, (end - time.time_ns()) / 1e9) + 0.05)
        src.open()
        frame = must(src.grab(1.0))
        assert frame.capture_unix_ns >= end
        assert last is not None and frame.frame_index > last.frame_index + 25
    finally:
        src.close()


def test_sim_prerendered_jpeg_content_repeats_and_default_epoch(world):
    src = sim(
        world,
        camera_index=1,
        epoch_unix_ns=None,
        pre_encode="jpeg",
        jpeg_quality=80,
        prerender_s=1.0,
        realtime=False,
    )
    with src:
        assert src.epoch_unix_ns % DAY_NS == 0  # the start of today, UTC
        assert src.epoch_unix_ns <= time.time_ns() < src.epoch_unix_ns + DAY_NS
        t0 = time.monotonic()
        frames = [must(src.grab(0.0)) for _ in range(80)]  # ~2.7 s of camera time
        assert time.monotonic() - t0 < 2.0  # not paced, and nothing is rendered any more
    assert all(f.left_bgr is None and f.encoded is not None for f in frames)
    assert len({id(f.encoded) for f in frames}) == 2  # 1 s of content at 2 fps, repeated
    pair = frames[0].encoded
    assert pair is not None and pair.encoding == "jpeg" and (pair.width, pair.height) == (960, 600)
    assert decode_image(pair.left, "jpeg", 960, 600).shape == (600, 960, 3)
    steps = np.diff([f.capture_unix_ns for f in frames])
    assert np.all(steps > 0)


def test_sim_epoch_in_the_future_is_refused(world):
    src = sim(world, epoch_unix_ns=time.time_ns() + 3600 * 10**9)
    with pytest.raises(ConfigError, match=r"epoch_unix_ns = .* is in the future"):
        src.open()
    assert not src.is_open


def test_sim_factory_conf_is_the_rig_file(world):
    src = sim(world, camera_index=2)
    text = src.factory_conf_text()
    cal = ZedFactoryCalibration.parse(text, serial=src.serial)
    assert cal.baseline_mm == world.rig[2].factory.baseline_mm
    assert "[LEFT_CAM_SVGA]" in text and src.resolution is Resolution.SVGA


def test_make_source_sim_and_config_errors(world):
    src = source_from_table(
        "sim",
        {"source": "sim", "seed": 11, "camera_index": 3, "resolution": "svga", "fps": 60},
        WHERE,
    )
    assert isinstance(src, SimSource)
    assert src.resolution is Resolution.SVGA and src.fps == 60.0
    assert src.serial == world.rig[3].serial
    assert src.config.content_fps == 2.0 and src.config.realtime and src.config.free_running

    def bad(table, *patterns):
        with pytest.raises(ConfigError) as info:
            source_from_table("sim", table, WHERE)
        for p in (re.escape(WHERE), *patterns):
            assert re.search(p, str(info.value)), (p, str(info.value))

    bad({"resolution": "4K"}, r"resolution = '4K'", "HD1200, HD1080, SVGA")
    bad({"camera_index": 7}, r"camera_index = 7", "0 to 3")
    bad({"resolution": "HD1200", "fps": 90}, r"fps = 90", "60")
    bad({"phase": "lunch"}, r"phase = 'lunch'", "intraoperative")
    bad({"pre_encode": "png"}, r"pre_encode = 'png'", "'jpeg'")
    bad({"epoch_unix_ns": "today"}, r"epoch_unix_ns = 'today'")
    bad({"fsp": 30}, "unknown option.*fsp", "fps")
    bad({"faults": [{"kind": "explode", "at_s": 1, "duration_s": 1}]}, r"faults\[0\]", "'hang'")
    bad({"faults": [{"kind": "hang", "at_s": 1}]}, r"faults\[0\]", "duration_s")
    bad({"drop_probability": 0.7}, "drop_probability = 0.7")
    with pytest.raises(ConfigError, match=r"source = 'gige'.*'sim', 'zed', 'video'"):
        source_from_table("gige", {}, WHERE)


def test_sources_import_without_the_simulator_or_the_sdk():
    """The agent on a Jetson imports every backend module but sim's without sim/ or numba."""
    imports = (
        "import capture_agent.sources, capture_agent.agent.ptp, protocol.images\n"
        "from capture_agent.sources import zed_source, video_source"
    )
    assert heavy_modules_after(imports, ("sim", "numba", "torch", "open3d", "pyzed")) == []


# ---- video -------------------------------------------------------------------------------------
def write_video(path: Path, frames: list[np.ndarray], fps: float) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def solid(h: int, w: int, bgr: tuple[int, int, int]) -> np.ndarray:
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = bgr
    return img


def test_video_side_by_side_replay(tmp_path):
    colours = [((30 * i, 60, 200), (200, 120, 30 * i)) for i in range(5)]
    sbs = [np.hstack([solid(600, 960, lc), solid(600, 960, rc)]) for lc, rc in colours]
    path = write_video(tmp_path / "sbs.avi", sbs, fps=25)
    conf = tmp_path / "SN7.conf"
    conf.write_text("[STEREO]\n")
    src = source_from_table(
        "video", {"path": str(path), "serial": 7, "conf_path": str(conf)}, WHERE
    )
    assert src.fps == 25.0 and src.resolution is Resolution.SVGA and src.serial == 7
    assert src.factory_conf_text() == "[STEREO]\n"
    with src:
        t0 = time.monotonic()
        frames = [must(src.grab(1.0)) for _ in range(5)]
        elapsed = time.monotonic() - t0
        with pytest.raises(EndOfRecordingError, match="ended"):
            src.grab(1.0)
    assert elapsed > 0.12  # paced at 25 fps: frame 4 is due 0.16 s after open
    assert [f.frame_index for f in frames] == list(range(5))
    first = frames[0].capture_unix_ns
    assert [f.capture_unix_ns - first for f in frames] == [round(i * 1e9 / 25) for i in range(5)]
    assert abs(first - frames[0].host_receive_unix_ns) < 1e9
    for f, (lc, rc) in zip(frames, colours, strict=True):
        assert left(f).shape == (600, 960, 3) and right(f).shape == (600, 960, 3)
        assert np.abs(left(f)[300, 480].astype(int) - lc).max() < 12
        assert np.abs(right(f)[300, 480].astype(int) - rc).max() < 12


def test_video_two_files_loop_and_resize(tmp_path):
    lefts = [solid(60, 96, (0, 0, 80 * i + 40)) for i in range(3)]
    rights = [solid(60, 96, (80 * i + 40, 0, 0)) for i in range(3)]
    table = {
        "left_path": str(write_video(tmp_path / "l.avi", lefts, fps=10)),
        "right_path": str(write_video(tmp_path / "r.avi", rights, fps=10)),
        "fps": 50,
        "loop": True,
        "realtime": False,
        "resolution": "SVGA",
    }
    with source_from_table("video", table, WHERE) as src:
        frames = [must(src.grab(0.0)) for _ in range(7)]
    assert [f.frame_index for f in frames] == list(range(7))
    assert [f.capture_unix_ns - frames[0].capture_unix_ns for f in frames] == [
        i * 20_000_000 for i in range(7)
    ]
    reds = [int(left(f)[30, 48, 2]) for f in frames]
    blues = [int(right(f)[30, 48, 0]) for f in frames]
    assert reds[:3] == pytest.approx([40, 120, 200], abs=12)
    assert reds[3:6] == reds[:3] and reds[6] == reds[0]  # looped, both sides together
    assert blues[:3] == pytest.approx([40, 120, 200], abs=12) and blues[3:6] == blues[:3]
    assert left(frames[0]).shape == (600, 960, 3)  # resized to SVGA


def test_video_realtime_grab_times_out_between_frames(tmp_path):
    path = write_video(tmp_path / "sbs.avi", [np.zeros((600, 1920, 3), np.uint8)] * 3, fps=25)
    with source_from_table("video", {"path": str(path), "fps": 4}, WHERE) as src:
        assert src.grab(1.0) is not None
        assert src.grab(0.05) is None  # the next frame is due 0.25 s after the first
        t0 = time.monotonic()
        frame = src.grab(1.0)
        assert frame is not None and frame.frame_index == 1
        assert time.monotonic() - t0 < 0.5


def test_video_config_errors(tmp_path):
    with pytest.raises(ConfigError, match=rf"{re.escape(WHERE)}: give either 'path'"):
        source_from_table("video", {}, WHERE)
    with pytest.raises(ConfigError, match="give either 'path'"):
        source_from_table("video", {"path": "a.avi", "left_path": "b.avi"}, WHERE)
    with pytest.raises(ConfigError, match="give either 'path'"):
        source_from_table("video", {"left_path": "b.avi"}, WHERE)
    with pytest.raises(ConfigError, match="fps = -1"):
        source_from_table("video", {"path": "a.avi", "fps": -1}, WHERE)
    with pytest.raises(ConfigError, match="does not exist"):
        source_from_table("video", {"path": str(tmp_path / "missing.avi")}, WHERE).open()
    small = write_video(tmp_path / "small.avi", [np.zeros((60, 192, 3), np.uint8)] * 2, fps=10)
    with pytest.raises(ConfigError, match=r"96x60 per side, not a ZED X mode.*'resolution'"):
        source_from_table("video", {"path": str(small)}, WHERE).open()
    other = write_video(tmp_path / "other.avi", [np.zeros((64, 96, 3), np.uint8)] * 2, fps=10)
    src = source_from_table(
        "video", {"left_path": str(small), "right_path": str(other), "resolution": "SVGA"}, WHERE
    )
    with pytest.raises(ConfigError, match="differ in frame size"):
        src.open()
    assert not src.is_open
