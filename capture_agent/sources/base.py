"""The camera seam: one small abstract class that every backend (sim, ZED X, video) implements.

A source delivers stereo frames with two timestamps, both Unix ns on the host's PTP-disciplined
system clock:

- ``capture_unix_ns``: the time the camera stamps on the frame. For a ZED X it is
  ``get_timestamp(sl.TIME_REFERENCE.IMAGE)``: the host clock when the frame was complete (after
  readout), not the start of exposure. Synchronised sets are grouped by this time.
- ``host_receive_unix_ns``: the host clock when our code got the frame, taken before any
  processing (conversion, encoding); ``host_receive - capture`` is the delivery latency.

``frame_index`` counts the camera's own frames from its free-running clock: a frame the camera
lost makes the index jump, so gaps are visible downstream.

Example::

    with make_source(SimSourceConfig(camera_index=0)) as cam:
        frame = cam.grab(timeout_s=1.0)      # None on timeout
        if frame is not None:
            frame.left_bgr.shape             # (600, 960, 3) uint8
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from types import TracebackType

import numpy as np

from protocol.camera import Resolution
from protocol.images import EncodedPair


@dataclass(frozen=True, kw_only=True)
class GrabbedFrame:
    """One stereo frame as a source delivers it.

    ``left_bgr``/``right_bgr`` are (H, W, 3) uint8 BGR; a source may share them between frames,
    so treat them as read-only. ``encoded`` is set when the source already holds encoded images
    (the sim's ``pre_encode``), so the agent need not encode again; at least one of the images
    or ``encoded`` is present.
    """

    frame_index: int
    capture_unix_ns: int
    host_receive_unix_ns: int
    left_bgr: np.ndarray | None = None
    right_bgr: np.ndarray | None = None
    encoded: EncodedPair | None = None

    @property
    def latency_ns(self) -> int:
        """Host receive time minus the camera's stamp."""
        return self.host_receive_unix_ns - self.capture_unix_ns


class CameraSource(abc.ABC):
    """A stereo camera. ``open()`` before ``grab()``; ``close()`` is idempotent.

    ``grab(timeout_s)`` returns the next frame, or ``None`` when none arrived within
    ``timeout_s`` (a hung camera), and raises ``CameraUnavailableError`` when the camera is gone;
    the caller then closes the source and calls ``open()`` again later (``open()`` raises the same
    error while the camera is still missing). The seam's errors live in ``capture_agent.errors``.
    """

    @property
    @abc.abstractmethod
    def serial(self) -> int:
        """The camera's serial number (0 if unknown)."""

    @property
    @abc.abstractmethod
    def resolution(self) -> Resolution: ...

    @property
    @abc.abstractmethod
    def fps(self) -> float: ...

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    @abc.abstractmethod
    def open(self) -> None: ...

    @abc.abstractmethod
    def grab(self, timeout_s: float) -> GrabbedFrame | None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def factory_conf_text(self) -> str:
        """The camera's ``SN<serial>.conf`` text, or ``""`` if unknown."""

    @property
    def name(self) -> str:
        return f"{type(self).__name__}(SN{self.serial})"

    def __enter__(self) -> CameraSource:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def require_timeout(timeout_s: float) -> float:
    t = float(timeout_s)
    if not t >= 0:
        raise ValueError(f"timeout_s={timeout_s} must be >= 0")
    return t
