"""Fake ``pyzed.sl`` as ZED SDK 5.x behaves, replaying PNG frames with their image timestamps.

The test writes ``replay.json`` into a directory and points ``REPLAY_DIR`` at it::

    {"serial": 41234567,
     "events": [{"timestamp_ns": 1767225600008000000, "left": "l0.png", "right": "r0.png"},
                {"timestamp_ns": ..., "left": ..., "right": ...,
                 "warning": "POTENTIAL_CALIBRATION_ISSUE"},
                {"error": "CAMERA_REBOOTING"},
                {"error": "CORRUPTED_FRAME"},
                {"wedge": true},
                {"error": "CAMERA_NOT_DETECTED"}]}

What it mimics of the SDK (names, signatures and values as Stereolabs documents them):

- ``ERROR_CODE`` with SDK 5's values: negative codes are warnings (``grab()`` still produced an
  image, except ``CORRUPTED_FRAME`` and ``CAMERA_REBOOTING``), ``SUCCESS`` is 0, positive codes are
  errors; members compare with ``<`` / ``>`` as pyzed's do; ``str()`` is the SDK's ``toString``.
- ``Camera.get_sdk_version()`` returns ``SDK_VERSION`` (a test sets "4.1.2" for an old SDK).
- ``Camera.open`` checks the serial (a wrong one is ``CAMERA_NOT_DETECTED``). The PNGs are the
  raw sensor images: ``VIEW.LEFT_UNRECTIFIED`` / ``RIGHT_UNRECTIFIED`` return them as they are,
  ``VIEW.LEFT`` / ``RIGHT`` return them rectified through the factory calibration
  ``SN<serial>.conf`` (from ``optional_settings_path``, else from the replay directory, as the SDK
  downloads it), with OpenCV's ``stereoRectify`` as the SDK does. No calibration file: open fails
  with ``CALIBRATION_FILE_NOT_AVAILABLE``.
- The camera opens in the mode asked for, unless ``replay.json`` names another ``resolution`` /
  ``fps`` (the mode the camera falls back to): then ``open`` returns the ``CONFIGURATION_FALLBACK``
  warning and ``get_camera_information()`` reports the mode actually opened.
- Each ``grab`` waits one frame period, then plays the next event: a frame (``SUCCESS``, or the
  event's ``warning`` code), an error code, or a wedge (``grab`` blocks until ``close()``, as a
  hung GMSL camera does). After the last event ``grab`` blocks until ``close()``.
  Every ``open`` replays from the first event.
"""

from __future__ import annotations

import configparser
import enum
import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np

REPLAY_DIR: Path | None = None
SDK_VERSION = "5.0.3"


class _Ordered(enum.Enum):
    """pyzed's enums compare by value (``err <= ERROR_CODE.SUCCESS``)."""

    def __lt__(self, other):
        return self.value < other.value if isinstance(other, type(self)) else NotImplemented

    def __le__(self, other):
        return self.value <= other.value if isinstance(other, type(self)) else NotImplemented

    def __gt__(self, other):
        return self.value > other.value if isinstance(other, type(self)) else NotImplemented

    def __ge__(self, other):
        return self.value >= other.value if isinstance(other, type(self)) else NotImplemented


class ERROR_CODE(_Ordered):  # the SDK spells its enums in capitals
    SENSOR_CONFIGURATION_CHANGED = -6
    POTENTIAL_CALIBRATION_ISSUE = -5
    CONFIGURATION_FALLBACK = -4
    SENSORS_DATA_REQUIRED = -3
    CORRUPTED_FRAME = -2
    CAMERA_REBOOTING = -1
    SUCCESS = 0
    FAILURE = 1
    NO_GPU_COMPATIBLE = 2
    NOT_ENOUGH_GPU_MEMORY = 3
    CAMERA_NOT_DETECTED = 4
    SENSORS_NOT_INITIALIZED = 5
    SENSORS_NOT_AVAILABLE = 6
    INVALID_RESOLUTION = 7
    LOW_USB_BANDWIDTH = 8
    CALIBRATION_FILE_NOT_AVAILABLE = 9
    INVALID_CALIBRATION_FILE = 10
    INVALID_FUNCTION_PARAMETERS = 16
    CAMERA_NOT_INITIALIZED = 18

    def __str__(self) -> str:  # sl::toString: words, not the member's name
        return self.name.replace("_", " ")


class RESOLUTION(_Ordered):
    HD4K = 0
    QHDPLUS = 1
    HD2K = 2
    HD1536 = 3
    HD1080 = 4
    HD1200 = 5
    HD720 = 6
    SVGA = 7
    VGA = 8
    AUTO = 9


class VIEW(_Ordered):
    LEFT = 0
    RIGHT = 1
    LEFT_GRAY = 2
    RIGHT_GRAY = 3
    LEFT_UNRECTIFIED = 4
    RIGHT_UNRECTIFIED = 5


class TIME_REFERENCE(_Ordered):
    IMAGE = 0
    CURRENT = 1


class MEM(_Ordered):
    CPU = 0
    GPU = 1


class DEPTH_MODE(_Ordered):
    NONE = 0
    PERFORMANCE = 1


class MODEL(_Ordered):
    ZED_X = 4


# The ZED X's modes: (width, height) per side, the frame rates each runs at, and the section
# suffix in SN<serial>.conf.
_SIZES = {
    RESOLUTION.HD1200: (1920, 1200),
    RESOLUTION.HD1080: (1920, 1080),
    RESOLUTION.SVGA: (960, 600),
}
_CONF = {RESOLUTION.HD1200: "FHD1200", RESOLUTION.HD1080: "FHD", RESOLUTION.SVGA: "SVGA"}


class Resolution:
    def __init__(self, width: int = 0, height: int = 0) -> None:
        self.width = width
        self.height = height


class InitParameters:
    def __init__(self) -> None:
        self.camera_resolution = RESOLUTION.AUTO
        self.camera_fps = 0
        self.depth_mode = DEPTH_MODE.PERFORMANCE
        self.optional_settings_path = ""
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

    def get_data(self, memory_type: MEM = MEM.CPU, deep_copy: bool = False) -> np.ndarray:
        return self._data.copy() if deep_copy else self._data

    def get_width(self) -> int:
        return self._data.shape[1]

    def get_height(self) -> int:
        return self._data.shape[0]


class CameraConfiguration:
    def __init__(self, resolution: Resolution, fps: float) -> None:
        self.resolution = resolution
        self.fps = fps


class CameraInformation:
    def __init__(self, serial_number: int, configuration: CameraConfiguration) -> None:
        self.serial_number = serial_number
        self.camera_model = MODEL.ZED_X
        self.camera_configuration = configuration


class DeviceProperties:
    def __init__(self, serial_number: int) -> None:
        self.serial_number = serial_number
        self.camera_model = MODEL.ZED_X


def _rectify_maps(conf_path: Path, res: RESOLUTION) -> tuple | None:
    """OpenCV remap tables from the raw to the rectified views of ``conf_path``; None when the
    file lacks what the mode needs. The 8-term rational model when [LEFT_DISTO] is complete."""
    ini = configparser.ConfigParser(interpolation=None, strict=False)
    ini.optionxform = str  # type: ignore[assignment,method-assign]
    ini.read_string(conf_path.read_text())
    width, height = _SIZES[res]
    scale = 0.5 if res is RESOLUTION.SVGA else 1.0
    dy = -60.0 if res is RESOLUTION.HD1080 else 0.0
    cams = []
    try:
        for side in ("LEFT", "RIGHT"):
            sec = ini[f"{side}_CAM_FHD1200"]  # the other modes derive from it, as on a ZED X
            K = np.array(
                [
                    [float(sec["fx"]) * scale, 0, float(sec["cx"]) * scale],
                    [0, float(sec["fy"]) * scale, (float(sec["cy"]) + dy) * scale],
                    [0, 0, 1],
                ]
            )
            keys = ("k1", "k2", "p1", "p2", "k3")
            dist = [float(sec[k]) for k in keys]
            disto = f"{side}_DISTO"
            rational = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
            if ini.has_section(disto) and all(k in ini[disto] for k in rational):
                dist = [float(ini[disto][k]) for k in rational]
            cams.append((K, np.array(dist)))
        st = ini["STEREO"]
        suf = _CONF[res] if f"RX_{_CONF[res]}" in st else "FHD1200"
        rvec = np.array([float(st[f"{a}_{suf}"]) for a in ("RX", "CV", "RZ")])
        T = np.array([-float(st["Baseline"]), float(st["TY"]), float(st["TZ"])])
    except KeyError:
        return None
    R, _ = cv2.Rodrigues(rvec)
    (K1, d1), (K2, d2) = cams
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, d1, K2, d2, (width, height), R, T, alpha=0)
    left = cv2.initUndistortRectifyMap(K1, d1, R1, P1, (width, height), cv2.CV_32FC1)
    right = cv2.initUndistortRectifyMap(K2, d2, R2, P2, (width, height), cv2.CV_32FC1)
    return left, right


class Camera:
    def __init__(self) -> None:
        self._events: list[dict] = []
        self._serial = 0
        self._period_s = 1 / 30
        self._next_grab = 0.0
        self._raw: dict[str, np.ndarray] = {}
        self._maps: tuple | None = None
        self._config = CameraConfiguration(Resolution(), 0.0)
        self._stamp_ns = 0
        self._closed = threading.Event()

    @staticmethod
    def get_sdk_version() -> str:
        return SDK_VERSION

    @staticmethod
    def get_device_list() -> list[DeviceProperties]:
        if REPLAY_DIR is None or not (Path(REPLAY_DIR) / "replay.json").exists():
            return []
        return [
            DeviceProperties(json.loads((Path(REPLAY_DIR) / "replay.json").read_text())["serial"])
        ]

    def open(self, init: InitParameters) -> ERROR_CODE:
        devices = self.get_device_list()
        if not devices or init.serial_number not in (None, devices[0].serial_number):
            return ERROR_CODE.CAMERA_NOT_DETECTED
        assert REPLAY_DIR is not None
        replay = json.loads((Path(REPLAY_DIR) / "replay.json").read_text())
        asked = init.camera_resolution
        if asked is RESOLUTION.AUTO:
            asked = RESOLUTION.HD1200
        if asked not in _SIZES:
            return ERROR_CODE.INVALID_RESOLUTION
        res = RESOLUTION[replay.get("resolution", asked.name)]
        fps = int(replay.get("fps", init.camera_fps or 30))
        self._serial = int(replay["serial"])
        name = f"SN{self._serial}.conf"
        candidates = [
            Path(init.optional_settings_path or "/nonexistent") / name,
            Path(REPLAY_DIR) / name,
        ]
        conf = next((p for p in candidates if p.is_file()), None)
        if conf is None:
            return ERROR_CODE.CALIBRATION_FILE_NOT_AVAILABLE
        self._maps = _rectify_maps(conf, res)
        if self._maps is None:
            return ERROR_CODE.INVALID_CALIBRATION_FILE
        self._config = CameraConfiguration(Resolution(*_SIZES[res]), float(fps))
        self._events = list(replay["events"])
        self._period_s = 1.0 / fps
        self._next_grab = time.monotonic()
        self._closed.clear()
        if res is not asked or fps != init.camera_fps:
            return ERROR_CODE.CONFIGURATION_FALLBACK
        return ERROR_CODE.SUCCESS

    def grab(self, runtime: RuntimeParameters | None = None) -> ERROR_CODE:
        if not self._events or self._events[0].get("wedge"):
            self._closed.wait()
            return ERROR_CODE.CAMERA_NOT_INITIALIZED
        self._next_grab += self._period_s
        time.sleep(max(0.0, self._next_grab - time.monotonic()))
        event = self._events.pop(0)
        if "error" in event:
            return ERROR_CODE[event["error"]]
        for side in ("left", "right"):
            bgr = cv2.imread(str(Path(REPLAY_DIR or ".") / event[side]), cv2.IMREAD_COLOR)
            assert bgr is not None, f"fake pyzed: cannot read {event[side]}"
            self._raw[side] = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
        self._stamp_ns = int(event["timestamp_ns"])
        return ERROR_CODE[event.get("warning", "SUCCESS")]

    def retrieve_image(
        self, py_mat: Mat, view: VIEW = VIEW.LEFT, mem_type: MEM = MEM.CPU, resolution=None
    ) -> ERROR_CODE:
        if not self._raw:
            return ERROR_CODE.CAMERA_NOT_INITIALIZED
        if view in (VIEW.LEFT_UNRECTIFIED, VIEW.RIGHT_UNRECTIFIED):
            py_mat._data = self._raw["left" if view is VIEW.LEFT_UNRECTIFIED else "right"].copy()
        elif view in (VIEW.LEFT, VIEW.RIGHT):
            assert self._maps is not None
            side = 0 if view is VIEW.LEFT else 1
            raw = self._raw["left" if side == 0 else "right"]
            mapx, mapy = self._maps[side]
            py_mat._data = cv2.remap(raw, mapx, mapy, cv2.INTER_LINEAR)
        else:
            return ERROR_CODE.INVALID_FUNCTION_PARAMETERS
        return ERROR_CODE.SUCCESS

    def get_timestamp(self, time_reference: TIME_REFERENCE) -> Timestamp:
        if time_reference is TIME_REFERENCE.IMAGE:
            return Timestamp(self._stamp_ns)
        return Timestamp(time.time_ns())

    def get_camera_information(self, resizer: Resolution | None = None) -> CameraInformation:
        return CameraInformation(self._serial, self._config)

    def close(self) -> None:
        self._closed.set()
