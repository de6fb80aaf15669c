"""The ZED X through the ZED SDK's Python API (``pyzed.sl``).

``pyzed`` is imported when a ``ZedSource`` is constructed, never when this package is imported,
so a node without the SDK runs the ``sim`` and ``video`` sources and fails only when a ``zed``
source is asked for, with a message that says what to install.

What the SDK gives (5.x, the version this needs), and what we take from it:

- ``sl.Camera.get_sdk_version()``: below 5.0 the source refuses to start, in one line. pyzed 4.x
  holds the GIL through ``grab()`` (two cameras, the encoders and the publisher would take turns)
  and its wheels predate NumPy 2.
- ``sl.Camera.open(sl.InitParameters)`` with ``camera_resolution`` (``sl.RESOLUTION.HD1200``,
  ``HD1080``, ``SVGA``), ``camera_fps``, ``depth_mode = NONE`` (we only need the images),
  ``optional_settings_path`` (the folder of the ``SN<serial>.conf`` we store) and
  ``set_from_serial_number(serial)`` to pick one of the node's two cameras. SDK 5 codes below
  ``SUCCESS`` are warnings, above it errors; the SDK may fall back to another mode
  (``CONFIGURATION_FALLBACK``), so the resolution and fps it chose are read back from
  ``get_camera_information().camera_configuration`` and a camera not in the configured mode is
  refused, naming both;
- ``grab()`` blocks until the next frame. ``SUCCESS`` and the warnings that come with an image
  (``POTENTIAL_CALIBRATION_ISSUE``, ...) give a frame; ``CORRUPTED_FRAME`` (green or purple
  image) and ``CAMERA_REBOOTING`` (no new image) are skipped. Each warning is counted in
  ``grab_warnings`` and logged (its first time, then at most every ``WARNING_LOG_INTERVAL_S``);
  an error code means the camera is gone: ``CameraUnavailableError``;
- ``retrieve_image(mat, sl.VIEW.LEFT_UNRECTIFIED / RIGHT_UNRECTIFIED)``: the raw sensor images,
  BGRA (``U8_C4``), converted to BGR (a copy, so the Mat can be refilled). Not ``VIEW.LEFT`` /
  ``RIGHT``: those are the SDK's rectified views, and calibration and reconstruction treat frames
  as distorted sensor images that they rectify themselves from ``SN<serial>.conf``;
- ``get_timestamp(sl.TIME_REFERENCE.IMAGE).get_nanoseconds()``: the host system clock (PTP
  disciplined) when the frame was complete, our ``capture_unix_ns``.

A live ZED X has no frame counter in the API, so ``frame_index`` counts frame periods between
image stamps: ``index += max(1, round(dt / period))``, 0 for the first frame after ``open()``;
a frame the camera lost shows as a gap.

``grab()`` runs in a grab thread that hands frames over a small queue, so ``grab(timeout_s)``
returns ``None`` on time even when the SDK hangs; if the consumer falls behind, the oldest frame
is dropped (``overrun_frames``), as the SDK itself does. A wedged camera (a GMSL camera whose
``grab()`` never returns) therefore reads as "no frame": the agent's worker closes and reopens
it after ``watchdog_timeout_s``. ``close()`` waits a bounded time for the SDK and abandons a
camera object whose ``close()`` hangs too, so the reopen is never stuck behind it.

The factory calibration is the SDK's own file, ``<settings_dir>/SN<serial>.conf``.

Example ``node.toml`` table::

    [[cameras]]
    source = "zed"
    serial = 41234567
    resolution = "HD1200"
    fps = 30
"""

from __future__ import annotations

import collections
import logging
import queue
import re
import threading
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2

from capture_agent.errors import CameraUnavailableError, SdkMissingError
from capture_agent.sources.base import CameraSource, GrabbedFrame, require_timeout
from protocol.camera import Resolution
from protocol.formats.camera_config import ZedSourceConfig

log = logging.getLogger(__name__)

MIN_SDK_VERSION = (5, 0)
WARNING_LOG_INTERVAL_S = 10.0
SDK_CLOSE_TIMEOUT_S = 5.0  # the SDK's close() of a healthy ZED X takes well under a second
# Warnings that come without a usable image: the frame is skipped (it shows as an index gap).
SKIPPED_WARNINGS = ("CORRUPTED_FRAME", "CAMERA_REBOOTING")

INSTALL_HINT = (
    "install the ZED SDK for this machine (ZED X on a Jetson: the SDK for its JetPack, from "
    "https://www.stereolabs.com/developers/release), then install its Python API into this "
    "environment with `python /usr/local/zed/get_python_api.py` using this environment's python; "
    'or use source = "sim" or "video" on a machine without cameras'
)


def import_pyzed() -> ModuleType:
    try:
        import pyzed.sl as sl
    except ImportError as exc:
        if (exc.name or "").split(".")[0] == "pyzed":
            raise SdkMissingError(
                f"the 'zed' camera source needs pyzed, the ZED SDK's Python API: {INSTALL_HINT}"
            ) from None
        raise SdkMissingError(
            f"pyzed is installed but does not load ({exc}); the ZED SDK libraries are missing "
            f"or do not match it: {INSTALL_HINT}"
        ) from None
    return sl


def sdk_version(sl: ModuleType) -> str:
    """The installed ZED SDK's version, as ``sl.Camera.get_sdk_version()`` reports it."""
    return str(sl.Camera.get_sdk_version())


def require_sdk_version(sl: ModuleType) -> str:
    """The SDK version, or ``SdkMissingError`` (one line) when it is older than 5.0."""
    found = sdk_version(sl)
    m = re.match(r"\s*(\d+)\.(\d+)", found)
    if m is None or (int(m.group(1)), int(m.group(2))) < MIN_SDK_VERSION:
        need = ".".join(map(str, MIN_SDK_VERSION))
        raise SdkMissingError(
            f"ZED SDK {found} found; the 'zed' camera source needs ZED SDK >= {need} (4.x holds "
            f"the GIL while grabbing and predates NumPy 2): {INSTALL_HINT}"
        )
    return found


def code_name(err: Any) -> str:
    """An SDK code's enum name (``CAMERA_NOT_DETECTED``; its ``str()`` is the SDK's wording)."""
    return str(getattr(err, "name", err))


class ZedSource(CameraSource):
    def __init__(self, config: ZedSourceConfig) -> None:
        self.config = config
        self._sl = import_pyzed()
        self.sdk_version = require_sdk_version(self._sl)
        self._serial = config.serial or 0
        self._cam: Any = None
        self._queue: queue.Queue[GrabbedFrame | CameraUnavailableError] = queue.Queue()
        self._failure: CameraUnavailableError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.overrun_frames = 0
        self.corrupted_frames = 0
        self.grab_warnings: collections.Counter[str] = collections.Counter()
        self._warning_logged_at: dict[str, float] = {}

    @property
    def serial(self) -> int:
        return self._serial

    @property
    def resolution(self) -> Resolution:
        return self.config.resolution

    @property
    def fps(self) -> float:
        return float(self.config.fps)

    @property
    def is_open(self) -> bool:
        return self._cam is not None

    def open(self) -> None:
        if self._cam is not None and self._failure is None:
            return
        self.close()
        sl = self._sl
        init = sl.InitParameters()
        init.camera_resolution = getattr(sl.RESOLUTION, self.config.resolution.value)
        init.camera_fps = int(self.config.fps)
        init.depth_mode = sl.DEPTH_MODE.NONE
        init.optional_settings_path = str(self.config.settings_dir)
        if self.config.serial is not None:
            init.set_from_serial_number(int(self.config.serial))
        cam = sl.Camera()
        err = cam.open(init)
        which = f"SN{self.config.serial}" if self.config.serial else "(any serial)"
        if err > sl.ERROR_CODE.SUCCESS:  # SDK 5: below SUCCESS is a warning, above an error
            cam.close()
            raise CameraUnavailableError(
                f"ZED X {which} did not open: {code_name(err)}; check its cable and power, and "
                "that ZED_Explorer --all lists it"
            )
        if err != sl.ERROR_CODE.SUCCESS:
            log.warning("ZED X %s opened with a warning: %s", which, code_name(err))
        info = cam.get_camera_information()
        self._refuse_other_mode(cam, info.camera_configuration, which)
        self._serial = int(info.serial_number)
        self._cam = cam
        self._failure = None
        self._queue = queue.Queue(maxsize=self.config.buffer_frames)
        # Each grab thread its own stop flag: one abandoned in a wedged grab() must stay stopped
        # when it wakes after the camera was reopened.
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._grab_loop,
            args=(cam, self._queue, self._stop),
            name=f"zed-SN{self._serial}",
        )
        self._thread.daemon = True
        self._thread.start()
        log.info("opened ZED X SN%d at %s %d fps", self._serial, self.resolution.value, self.fps)

    def _refuse_other_mode(self, cam: Any, opened: Any, which: str) -> None:
        """The SDK may open another mode than asked (a fallback): refuse it, naming both."""
        want_w, want_h = self.config.resolution.size
        got_w, got_h = int(opened.resolution.width), int(opened.resolution.height)
        got_fps = float(opened.fps)
        if (got_w, got_h) == (want_w, want_h) and round(got_fps) == int(self.config.fps):
            return
        cam.close()
        raise CameraUnavailableError(
            f"ZED X {which} opened at {got_w}x{got_h} {got_fps:g} fps, not the configured "
            f"{self.config.resolution.value} ({want_w}x{want_h}) at {self.config.fps} fps; "
            "set resolution and fps in node.toml to a mode this camera runs (ZED_Explorer shows "
            "them), or check its cable (a GMSL link that cannot carry the mode)"
        )

    def close(self) -> None:
        cam, self._cam = self._cam, None
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=max(0.25, 3.0 / self.fps))  # grab() returns each frame
            if self._thread.is_alive():
                log.warning(
                    "SN%d: the grab thread is stuck in the SDK; closing anyway", self.serial
                )
        if cam is not None:
            self._close_sdk_camera(cam)
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        self._failure = None

    def _close_sdk_camera(self, cam: Any) -> None:
        """``cam.close()`` within ``SDK_CLOSE_TIMEOUT_S``: a wedged camera's close can hang as
        its grab did, and the reopen must not wait behind it (the object is abandoned)."""
        closer = threading.Thread(target=cam.close, name=f"zed-close-SN{self._serial}")
        closer.daemon = True
        closer.start()
        closer.join(timeout=SDK_CLOSE_TIMEOUT_S)
        if closer.is_alive():
            log.error(
                "SN%d: the SDK's close() has not returned after %.0f s; abandoning that camera "
                "object (if it does not reopen, restart nvargus-daemon and zed_x_daemon)",
                self._serial,
                SDK_CLOSE_TIMEOUT_S,
            )

    def grab(self, timeout_s: float) -> GrabbedFrame | None:
        if self._failure is not None:
            raise self._failure
        if self._cam is None:
            raise RuntimeError(f"{self.name} is not open; call open() first")
        try:
            item = self._queue.get(timeout=require_timeout(timeout_s))
        except queue.Empty:
            return None
        if isinstance(item, CameraUnavailableError):
            self._failure = item
            raise item
        return item

    def factory_conf_text(self) -> str:
        if not self._serial:
            return ""
        path = Path(self.config.settings_dir) / f"SN{self._serial}.conf"
        try:
            return path.read_text()
        except OSError as exc:
            log.warning(
                "SN%d: no factory calibration at %s (%s); the SDK downloads it on first open",
                self._serial,
                path,
                exc.strerror,
            )
            return ""

    # ---- the grab thread -------------------------------------------------------------------
    def _grab_loop(
        self,
        cam: Any,
        out: queue.Queue[GrabbedFrame | CameraUnavailableError],
        stop: threading.Event,
    ) -> None:
        sl = self._sl
        runtime = sl.RuntimeParameters()
        left, right = sl.Mat(), sl.Mat()
        period_ns = 1e9 / self.fps
        index, prev_ns = -1, 0
        while not stop.is_set():
            err = cam.grab(runtime)
            host_receive_unix_ns = time.time_ns()
            if stop.is_set():
                return
            if err > sl.ERROR_CODE.SUCCESS:
                lost = f"ZED X SN{self._serial}: grab: {code_name(err)}"
                self._put(out, CameraUnavailableError(lost))
                return
            if err != sl.ERROR_CODE.SUCCESS and self._warned(code_name(err)):
                continue
            stamp_ns = int(cam.get_timestamp(sl.TIME_REFERENCE.IMAGE).get_nanoseconds())
            for mat, view in ((left, sl.VIEW.LEFT_UNRECTIFIED), (right, sl.VIEW.RIGHT_UNRECTIFIED)):
                err = cam.retrieve_image(mat, view)
                if err > sl.ERROR_CODE.SUCCESS:
                    lost = f"ZED X SN{self._serial}: retrieve_image: {code_name(err)}"
                    self._put(out, CameraUnavailableError(lost))
                    return
            index = 0 if index < 0 else index + max(1, round((stamp_ns - prev_ns) / period_ns))
            prev_ns = stamp_ns
            frame = GrabbedFrame(
                frame_index=index,
                capture_unix_ns=stamp_ns,
                host_receive_unix_ns=host_receive_unix_ns,
                left_bgr=cv2.cvtColor(left.get_data(), cv2.COLOR_BGRA2BGR),
                right_bgr=cv2.cvtColor(right.get_data(), cv2.COLOR_BGRA2BGR),
            )
            self._put(out, frame)

    def _warned(self, name: str) -> bool:
        """Count and log an SDK 5 warning from ``grab()``; True when its frame is skipped."""
        self.grab_warnings[name] += 1
        skipped = name in SKIPPED_WARNINGS
        if name == "CORRUPTED_FRAME":
            self.corrupted_frames += 1
        now = time.monotonic()
        if (
            now - self._warning_logged_at.get(name, -WARNING_LOG_INTERVAL_S)
            >= WARNING_LOG_INTERVAL_S
        ):
            self._warning_logged_at[name] = now
            log.warning(
                "SN%d: grab() warned %s (%d so far)%s",
                self._serial,
                name,
                self.grab_warnings[name],
                "; frame skipped" if skipped else "",
            )
        return skipped

    def _put(
        self,
        out: queue.Queue[GrabbedFrame | CameraUnavailableError],
        item: GrabbedFrame | CameraUnavailableError,
    ) -> None:
        while True:
            try:
                out.put_nowait(item)
                return
            except queue.Full:
                try:
                    out.get_nowait()  # the consumer is behind: the oldest frame goes
                    self.overrun_frames += 1
                except queue.Empty:
                    pass
