"""A ``[[cameras]]`` table of node.toml: one config per camera source, told apart by ``source``.

``CameraConfig`` is the tagged union of ``SimSourceConfig`` (``source = "sim"``),
``ZedSourceConfig`` (``"zed"``) and ``VideoSourceConfig`` (``"video"``); node.toml's tables are
read into them when the node config loads, so a typo in a camera table fails at load, naming the
file, the table and the field. The sources (``capture_agent/sources/``) take these objects, and
the simulator's deploy (``sim/deploy.py``) builds them. A sim camera's phase and index are checked
against the simulated rig's names stated here (``SIM_PHASES``, ``SIM_RIG_CAMERAS``), which the
simulator implements (``sim.phases.PHASES`` is ``SIM_PHASES``; tests/sim/test_deploy.py checks
the mounts).

Example::

    cam = read_table(CameraConfig, {"source": "zed", "serial": 41234567}, "node.toml")
    cam.fps   # 30
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from protocol.camera import Resolution
from protocol.config_fields import check, option, validate
from protocol.errors import ConfigError

FaultKind = Literal["hang", "vanish"]
DEFAULT_SETTINGS_DIR = "/usr/local/zed/settings"
# What a sim camera table may name: the simulator's workflow phases and its rig's camera count.
# They are the table's contract, so they live with it (protocol/ may not import sim/).
SIM_PHASES = ("empty", "setup", "intraoperative", "turnover", "wand")
SIM_RIG_CAMERAS = 4


def zed_fps_modes(resolution: Resolution) -> tuple[int, ...]:
    return (15, 30, 60, 120) if resolution is Resolution.SVGA else (15, 30, 60)


@dataclass(frozen=True, kw_only=True)
class FaultSpec:
    """``kind`` ("hang" or "vanish") from ``at_s`` to ``at_s + duration_s`` after the first open."""

    kind: FaultKind
    at_s: float = option(ge=0, must="must be >= 0 (seconds after open)")
    duration_s: float = option(gt=0, must="must be > 0 seconds")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class SimSourceConfig:
    """Options of the ``sim`` source; clock defaults match ``sim.timing.ClockSpec``."""

    source: Literal["sim"] = "sim"
    seed: int = option(0, ge=0, must="must be an int >= 0")
    phase: str = "intraoperative"
    camera_index: int = 0
    resolution: Resolution = Resolution.SVGA
    fps: float = 30.0
    free_running: bool = True
    jitter_ns_std: float = option(150_000.0, ge=0)
    drop_probability: float = option(0.002, ge=0, lt=0.5, must="must be in [0, 0.5)")
    epoch_unix_ns: int | None = option(
        None, ge=0, must="must be a Unix time in ns (>= 0), shared by every agent of the rig"
    )
    content_fps: float = 2.0
    # "none" in a file: leave it out (frames are encoded by the agent)
    pre_encode: Literal["jpeg", "none"] | None = None
    jpeg_quality: int = option(90, ge=1, le=100, must="must be an integer from 1 to 100")
    prerender_s: float = option(0.0, ge=0, must="must be >= 0 seconds")
    realtime: bool = True
    faults: tuple[FaultSpec, ...] = ()

    def __post_init__(self) -> None:
        validate(self)
        if self.pre_encode == "none":
            object.__setattr__(self, "pre_encode", None)
        check(
            self.phase in SIM_PHASES,
            "phase",
            self.phase,
            f"choose one of {', '.join(SIM_PHASES)}",
        )
        n = SIM_RIG_CAMERAS
        check(
            0 <= self.camera_index < n,
            "camera_index",
            self.camera_index,
            f"the simulated rig has {n} cameras: choose 0 to {n - 1}",
        )
        res = self.resolution
        check(
            0 < self.fps <= res.max_fps,
            "fps",
            self.fps,
            f"must be > 0 and at most {res.max_fps} at {res.value} (ZED X: 15, 30, 60"
            + (", 120)" if res.max_fps > 60 else ")"),
        )
        check(
            0 < self.content_fps <= self.fps,
            "content_fps",
            self.content_fps,
            f"must be > 0 and at most fps ({self.fps})",
        )


@dataclass(frozen=True, kw_only=True)
class ZedSourceConfig:
    """A ZED X through the ZED SDK; ``serial = None`` opens the first camera found (a bench)."""

    source: Literal["zed"] = "zed"
    serial: int | None = option(
        None, gt=0, must="must be the camera's serial number (see ZED_Explorer --all)"
    )
    resolution: Resolution = Resolution.HD1200
    fps: int = 30
    settings_dir: str = DEFAULT_SETTINGS_DIR
    buffer_frames: int = option(2, ge=1, le=16)

    def __post_init__(self) -> None:
        validate(self)
        modes = zed_fps_modes(self.resolution)
        check(
            self.fps in modes,
            "fps",
            self.fps,
            f"the ZED X at {self.resolution.value} runs at {', '.join(map(str, modes))} fps",
        )


@dataclass(frozen=True, kw_only=True)
class VideoSourceConfig:
    """A recorded stereo video: ``path`` (side by side) or ``left_path`` and ``right_path``."""

    source: Literal["video"] = "video"
    path: str | None = None
    left_path: str | None = None
    right_path: str | None = None
    fps: float | None = option(
        None, test=math.isfinite, gt=0, must="must be > 0, or left out to use the file's rate"
    )
    loop: bool = False
    realtime: bool = True
    resolution: Resolution | None = None
    serial: int = option(0, ge=0, must="must be >= 0 (0: unknown)")
    conf_path: str | None = None  # the camera's SN<serial>.conf

    def __post_init__(self) -> None:
        validate(self)
        two = self.left_path is not None or self.right_path is not None
        if (self.path is None) == (not two) or (two and None in (self.left_path, self.right_path)):
            raise ConfigError(
                "give either 'path' (one side-by-side video) or both 'left_path' and "
                f"'right_path' (two videos); got path={self.path!r}, "
                f"left_path={self.left_path!r}, right_path={self.right_path!r}"
            )

    @property
    def paths(self) -> tuple[str, ...]:
        if self.path is not None:
            return (self.path,)
        assert self.left_path is not None and self.right_path is not None
        return (self.left_path, self.right_path)


CameraConfig = SimSourceConfig | ZedSourceConfig | VideoSourceConfig
