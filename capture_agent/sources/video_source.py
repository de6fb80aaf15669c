"""A recorded stereo video, replayed through OpenCV as if it were a camera.

Either one side-by-side file (``path``: left image in the left half, right image in the right
half, as the ZED tools export) or two files (``left_path`` and ``right_path``).

Timestamps are synthetic, since a video file carries no host clock: frame ``i`` (counted from
``open()``, continuing across loops) is stamped ``open_unix_ns + round(i * 1e9 / fps)``, with
``fps`` from the config or else from the file. No frame is ever dropped. With ``realtime = true``
(the default) ``grab()`` waits until the wall clock reaches a frame's stamp; with ``false`` frames
come as fast as they are asked for and their stamps run ahead of the wall clock.

At the end of the file, ``loop = true`` starts again from the first frame; otherwise ``grab()``
raises ``EndOfRecordingError`` (a ``CameraUnavailableError``).

``resolution`` unset: the frame size must be a ZED X mode (1920x1200, 1920x1080, 960x600 per
side); set, every frame is resized to it.

Example ``node.toml`` table::

    [[cameras]]
    source = "video"
    path = "/data/replay/SN41234567_sbs.mp4"
    serial = 41234567
    conf_path = "/data/replay/SN41234567.conf"
    loop = true
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import cv2
import numpy as np

from capture_agent.errors import EndOfRecordingError
from capture_agent.sources.base import CameraSource, GrabbedFrame, require_timeout
from protocol.camera import Resolution
from protocol.errors import ConfigError
from protocol.formats.camera_config import VideoSourceConfig

log = logging.getLogger(__name__)


class VideoSource(CameraSource):
    def __init__(self, config: VideoSourceConfig) -> None:
        self.config = config
        self._caps: list[cv2.VideoCapture] = []
        self._fps: float | None = config.fps
        self._resolution: Resolution | None = config.resolution
        self._open_unix_ns = 0
        self._index = 0

    @property
    def serial(self) -> int:
        return self.config.serial

    @property
    def resolution(self) -> Resolution:
        if self._resolution is None:
            self._probe()
        assert self._resolution is not None
        return self._resolution

    @property
    def fps(self) -> float:
        if self._fps is None:
            self._probe()
        assert self._fps is not None
        return self._fps

    @property
    def is_open(self) -> bool:
        return bool(self._caps)

    def factory_conf_text(self) -> str:
        if self.config.conf_path is None:
            return ""
        try:
            return Path(self.config.conf_path).read_text()
        except OSError as exc:
            raise ConfigError(
                f"conf_path {self.config.conf_path}: cannot read it ({exc.strerror})"
            ) from None

    def open(self) -> None:
        if self._caps:
            return
        caps = [self._capture(p) for p in self.config.paths]
        self._caps = caps
        try:
            self._configure(caps)
        except Exception:
            self.close()
            raise
        self._index = 0
        self._open_unix_ns = time.time_ns()

    def close(self) -> None:
        for cap in self._caps:
            cap.release()
        self._caps = []

    def grab(self, timeout_s: float) -> GrabbedFrame | None:
        if not self._caps:
            raise RuntimeError(f"{self.name} is not open; call open() first")
        timeout = require_timeout(timeout_s)
        capture_unix_ns = self._open_unix_ns + round(self._index * 1e9 / self.fps)
        if self.config.realtime:
            wait = (capture_unix_ns - time.time_ns()) / 1e9
            if wait > timeout:
                time.sleep(timeout)
                return None
            if wait > 0:
                time.sleep(wait)
        images = self._read()
        host_receive_unix_ns = time.time_ns()
        if len(images) == 1:
            width = images[0].shape[1] // 2
            left, right = images[0][:, :width], images[0][:, width : 2 * width]
        else:
            left, right = images
        size = self.resolution.size
        frame = GrabbedFrame(
            frame_index=self._index,
            capture_unix_ns=capture_unix_ns,
            host_receive_unix_ns=host_receive_unix_ns,
            left_bgr=_fit(left, size),
            right_bgr=_fit(right, size),
        )
        self._index += 1
        return frame

    # ---- internals -------------------------------------------------------------------------
    def _capture(self, path: str) -> cv2.VideoCapture:
        if not Path(path).is_file():
            raise ConfigError(f"video file {path} does not exist")
        cap = cv2.VideoCapture(path)
        if not cap.isOpened():
            cap.release()
            raise ConfigError(f"OpenCV cannot read video {path}: is it a video file?")
        return cap

    def _probe(self) -> None:
        caps = [self._capture(p) for p in self.config.paths]
        try:
            self._configure(caps)
        finally:
            for cap in caps:
                cap.release()

    def _configure(self, caps: list[cv2.VideoCapture]) -> None:
        """Take fps and the per-side frame size from the file(s) unless the config sets them."""
        paths = self.config.paths
        if self._fps is None:
            fps = float(caps[0].get(cv2.CAP_PROP_FPS))
            if not (math.isfinite(fps) and fps > 0):
                raise ConfigError(f"video {paths[0]} does not say its frame rate; set 'fps'")
            self._fps = fps
        width = int(caps[0].get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(caps[0].get(cv2.CAP_PROP_FRAME_HEIGHT))
        if len(caps) == 1:
            width //= 2
        else:
            other = (
                int(caps[1].get(cv2.CAP_PROP_FRAME_WIDTH)),
                int(caps[1].get(cv2.CAP_PROP_FRAME_HEIGHT)),
            )
            if other != (width, height):
                raise ConfigError(
                    f"videos {paths[0]} ({width}x{height}) and {paths[1]} "
                    f"({other[0]}x{other[1]}) differ in frame size"
                )
        if self._resolution is None:
            for res in Resolution:
                if res.size == (width, height):
                    self._resolution = res
                    break
            else:
                modes = ", ".join(f"{r.value} {r.width}x{r.height}" for r in Resolution)
                raise ConfigError(
                    f"video {paths[0]} is {width}x{height} per side, not a ZED X mode ({modes}); "
                    "set 'resolution' to resize it"
                )

    def _read(self) -> list[np.ndarray]:
        images = self._read_all()
        if images is None and self.config.loop and self._index > 0:
            for cap in self._caps:  # every file restarts together, so the sides stay paired
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            images = self._read_all()
        if images is None:
            what = "cannot be read" if self._index == 0 else "ended"
            names = " / ".join(self.config.paths)
            raise EndOfRecordingError(f"video {names} {what} (frame {self._index})")
        return images

    def _read_all(self) -> list[np.ndarray] | None:
        images = []
        for cap in self._caps:
            ok, image = cap.read()
            if not ok or image is None:
                return None
            images.append(image)
        return images


def _fit(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if (image.shape[1], image.shape[0]) == size:
        return np.ascontiguousarray(image)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)
