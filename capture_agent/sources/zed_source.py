"""The ZED X through the ZED SDK's Python API (``pyzed.sl``).

``pyzed`` is imported when a ``ZedSource`` is constructed, never when this package is imported,
so a node without the SDK runs the ``sim`` and ``video`` sources and fails only when a ``zed``
source is asked for, with a message that says what to install.

What the SDK gives, and what we take from it:

- ``sl.Camera.open(sl.InitParameters)`` with ``camera_resolution`` (``sl.RESOLUTION.HD1200``,
  ``HD1080``, ``SVGA``), ``camera_fps``, ``depth_mode = NONE`` (we only need the images) and
  ``set_from_serial_number(serial)`` to pick one of the node's two cameras;
- ``grab()`` blocks until the next frame and returns ``sl.ERROR_CODE.SUCCESS``; any other code
  but ``CORRUPTED_FRAME`` (skipped) means the camera is gone: ``CameraUnavailableError``;
- ``retrieve_image(mat, sl.VIEW.LEFT / RIGHT)`` fills an ``sl.Mat`` with BGRA (``U8_C4``), which we
  convert to BGR (a copy, so the Mat can be refilled);
- ``get_timestamp(sl.TIME_REFERENCE.IMAGE).get_nanoseconds()``: the host system clock (PTP
  disciplined) when the frame was complete, our ``capture_unix_ns``.

A live ZED X has no frame counter in the API, so ``frame_index`` counts frame periods between
image stamps: ``index += max(1, round(dt / period))``, 0 for the first frame after ``open()``;
a frame the camera lost shows as a gap.

``grab()`` runs in a grab thread that hands frames over a small queue, so ``grab(timeout_s)``
returns ``None`` on time even when the SDK hangs; if the consumer falls behind, the oldest frame
is dropped (``overrun_frames``), as the SDK itself does.

The factory calibration is the SDK's own file, ``<settings_dir>/SN<serial>.conf``.

Example ``node.toml`` table::

    [[cameras]]
    source = "zed"
    serial = 41234567
    resolution = "HD1200"
    fps = 30
"""

from __future__ import annotations

import logging
import queue
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


class ZedSource(CameraSource):
    def __init__(self, config: ZedSourceConfig) -> None:
        self.config = config
        self._sl = import_pyzed()
        self._serial = config.serial or 0
        self._cam: Any = None
        self._queue: queue.Queue[GrabbedFrame | CameraUnavailableError] = queue.Queue()
        self._failure: CameraUnavailableError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.overrun_frames = 0
        self.corrupted_frames = 0

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
        if self.config.serial is not None:
            init.set_from_serial_number(int(self.config.serial))
        cam = sl.Camera()
        err = cam.open(init)
        if err != sl.ERROR_CODE.SUCCESS:
            cam.close()
            which = f"SN{self.config.serial}" if self.config.serial else "(any serial)"
            raise CameraUnavailableError(
                f"ZED X {which} did not open: {err}; check its cable and power, and that "
                "ZED_Explorer --all lists it"
            )
        self._serial = int(cam.get_camera_information().serial_number)
        self._cam = cam
        self._failure = None
        self._queue = queue.Queue(maxsize=self.config.buffer_frames)
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._grab_loop, args=(cam, self._queue), name=f"zed-SN{self._serial}"
        )
        self._thread.daemon = True
        self._thread.start()
        log.info("opened ZED X SN%d at %s %d fps", self._serial, self.resolution.value, self.fps)

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
            cam.close()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        self._failure = None

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
    def _grab_loop(self, cam: Any, out: queue.Queue[GrabbedFrame | CameraUnavailableError]) -> None:
        sl = self._sl
        runtime = sl.RuntimeParameters()
        left, right = sl.Mat(), sl.Mat()
        period_ns = 1e9 / self.fps
        index, prev_ns = -1, 0
        while not self._stop.is_set():
            err = cam.grab(runtime)
            host_receive_unix_ns = time.time_ns()
            if self._stop.is_set():
                return
            if err == getattr(sl.ERROR_CODE, "CORRUPTED_FRAME", None):
                self.corrupted_frames += 1
                log.warning("SN%d: corrupted frame skipped", self._serial)
                continue
            if err != sl.ERROR_CODE.SUCCESS:
                self._put(out, CameraUnavailableError(f"ZED X SN{self._serial}: grab: {err}"))
                return
            stamp_ns = int(cam.get_timestamp(sl.TIME_REFERENCE.IMAGE).get_nanoseconds())
            cam.retrieve_image(left, sl.VIEW.LEFT)
            cam.retrieve_image(right, sl.VIEW.RIGHT)
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
