"""Fake ``pyzed.sl`` (ZED SDK 4.x names) that replays PNG frames with their image timestamps.

The test writes ``replay.json`` into a directory and points ``REPLAY_DIR`` at it::

    {"serial": 41234567, "resolution": "SVGA", "fps": 30,
     "events": [{"timestamp_ns": 1767225600008000000, "left": "l0.png", "right": "r0.png"},
                {"error": "CORRUPTED_FRAME"},
                {"error": "CAMERA_NOT_DETECTED"}]}

``Camera.open`` checks the requested serial, resolution and fps like the SDK (a wrong serial is
``CAMERA_NOT_DETECTED``); each ``grab`` waits one frame period, as a camera does, then plays the
next event: a frame (``SUCCESS``, images retrieved as BGRA ``U8_C4`` like the SDK's) or an error
code. After the last event ``grab`` blocks until ``close()``, as the SDK does with no frames.
Every ``open`` replays from the first event.
"""

from __future__ import annotations

import enum
import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np

REPLAY_DIR: Path | None = None


class ERROR_CODE(enum.Enum):  # the SDK spells its enums in capitals
    SUCCESS = 0
    FAILURE = 1
    CAMERA_NOT_DETECTED = 3
    INVALID_RESOLUTION = 8
    CAMERA_NOT_INITIALIZED = 20
    CAMERA_REBOOTING = 24
    CORRUPTED_FRAME = 30

    def __str__(self) -> str:
        return self.name


class RESOLUTION(enum.Enum):
    HD2K = 0
    HD1080 = 1
    HD1200 = 2
    HD720 = 3
    SVGA = 4
    VGA = 5
    AUTO = 6


class VIEW(enum.Enum):
    LEFT = 0
    RIGHT = 1


class TIME_REFERENCE(enum.Enum):
    IMAGE = 0
    CURRENT = 1


class MEM(enum.Enum):
    CPU = 1
    GPU = 2


class DEPTH_MODE(enum.Enum):
    NONE = 0
    PERFORMANCE = 1


class MAT_TYPE(enum.Enum):
    U8_C4 = 9


class InitParameters:
    def __init__(self) -> None:
        self.camera_resolution = RESOLUTION.AUTO
        self.camera_fps = 0
        self.depth_mode = DEPTH_MODE.PERFORMANCE
        self.serial_number: int | None = None

    def set_from_serial_number(self, serial_number: int, bus_type: object = None) -> None:
        self.serial_number = int(serial_number)


class RuntimeParameters:
    pass


class Timestamp:
    def __init__(self, ns: int) -> None:
        self._ns = int(ns)

    def get_nanoseconds(self) -> int:
        return self._ns

    def get_milliseconds(self) -> int:
        return self._ns // 1_000_000


class Mat:
    def __init__(self) -> None:
        self._data = np.zeros((0, 0, 4), np.uint8)

    def get_data(self) -> np.ndarray:
        return self._data

    def get_width(self) -> int:
        return self._data.shape[1]

    def get_height(self) -> int:
        return self._data.shape[0]


class CameraInformation:
    def __init__(self, serial_number: int) -> None:
        self.serial_number = serial_number
        self.camera_model = "ZED X"


class Camera:
    def __init__(self) -> None:
        self._events: list[dict] = []
        self._serial = 0
        self._period_s = 1 / 30
        self._next_grab = 0.0
        self._images: dict[VIEW, np.ndarray] = {}
        self._stamp_ns = 0
        self._closed = threading.Event()

    def open(self, init: InitParameters) -> ERROR_CODE:
        if REPLAY_DIR is None:
            return ERROR_CODE.CAMERA_NOT_DETECTED
        replay = json.loads((Path(REPLAY_DIR) / "replay.json").read_text())
        if init.serial_number not in (None, replay["serial"]):
            return ERROR_CODE.CAMERA_NOT_DETECTED
        if init.camera_resolution is not RESOLUTION[replay["resolution"]]:
            return ERROR_CODE.INVALID_RESOLUTION
        if init.camera_fps != replay["fps"]:
            return ERROR_CODE.FAILURE
        self._serial = replay["serial"]
        self._events = list(replay["events"])
        self._period_s = 1.0 / replay["fps"]
        self._next_grab = time.monotonic()
        self._closed.clear()
        return ERROR_CODE.SUCCESS

    def grab(self, runtime: RuntimeParameters | None = None) -> ERROR_CODE:
        if not self._events:
            self._closed.wait()
            return ERROR_CODE.CAMERA_NOT_INITIALIZED
        self._next_grab += self._period_s
        time.sleep(max(0.0, self._next_grab - time.monotonic()))
        event = self._events.pop(0)
        if "error" in event:
            return ERROR_CODE[event["error"]]
        for view, key in ((VIEW.LEFT, "left"), (VIEW.RIGHT, "right")):
            bgr = cv2.imread(str(Path(REPLAY_DIR or ".") / event[key]), cv2.IMREAD_COLOR)
            assert bgr is not None, f"fake pyzed: cannot read {event[key]}"
            self._images[view] = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
        self._stamp_ns = int(event["timestamp_ns"])
        return ERROR_CODE.SUCCESS

    def retrieve_image(
        self, mat: Mat, view: VIEW = VIEW.LEFT, mem_type: MEM = MEM.CPU, resolution=None
    ) -> ERROR_CODE:
        mat._data = self._images[view].copy()
        return ERROR_CODE.SUCCESS

    def get_timestamp(self, time_reference: TIME_REFERENCE) -> Timestamp:
        if time_reference is TIME_REFERENCE.IMAGE:
            return Timestamp(self._stamp_ns)
        return Timestamp(time.time_ns())

    def get_camera_information(self) -> CameraInformation:
        return CameraInformation(self._serial)

    def close(self) -> None:
        self._closed.set()
