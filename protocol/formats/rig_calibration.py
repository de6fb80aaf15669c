"""The rig calibration file, ``calibration.toml``: written by ``egosurg calibrate``, read by the
reconstructor and by a later ``--refine`` or drift check.

Human-readable TOML, one ``[[sensors]]`` table per sensor (8 for four ZED X)::

    # EgoSurg rig calibration, format 1
    format_version = 1
    resolution = "HD1200"            # the mode the intrinsics below are for
    world_frame = "floor"            # "floor": z = 0 on the floor; or "camera:<sensor name>"
    conventions = "metres; OpenCV camera axes; pose is world-to-camera: x_cam = R @ x_world + t"

    [quality]                        # numbers a reviewer judges the calibration by
    reprojection_px_mean = 0.21
    wand_score = 0.12                # 100 * SD / mean of the measured wand length
    verdict = "pass"

    [[sensors]]
    name = "SN41234567-left"
    camera_serial = 41234567
    side = "left"
    width_px = 1920
    height_px = 1200
    fx_px = 741.2
    fy_px = 741.0
    cx_px = 958.3
    cy_px = 601.1
    dist = [-0.042, 0.018, 0.0001, -0.0001, -0.004]   # OpenCV k1 k2 p1 p2 k3 [k4 k5 k6]
    rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    translation_m = [0.0, 0.0, 0.0]

    [sensors.stats]                  # per-sensor statistics (optional)
    reprojection_px_mean = 0.19

``dist`` has five terms, or eight for a lens on OpenCV's rational model (as ZED X factory files
may give it). Every number keeps full precision (``repr`` of the float), so a write-read round
trip is exact.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol import __version__
from protocol.camera import Camera, Intrinsics, Pose, Resolution
from protocol.errors import UserError
from protocol.formats.camera_toml import camera_lines, read_camera
from protocol.formats.camera_toml import toml_value as _v
from protocol.toml_config import parse_toml

CALIBRATION_FORMAT_VERSION = 1


class CalibrationFileError(UserError, ValueError):
    """A calibration file that cannot be used; the message names the file and the field."""


@dataclass(frozen=True, kw_only=True)
class SensorCalibration:
    name: str
    camera_serial: int
    side: str  # "left" or "right"
    intrinsics: Intrinsics
    pose: Pose  # world-to-camera
    stats: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.side not in ("left", "right"):
            raise CalibrationFileError(f"sensor {self.name}: side must be 'left' or 'right'")

    @property
    def camera(self) -> Camera:
        return Camera(name=self.name, intrinsics=self.intrinsics, pose=self.pose)


@dataclass(frozen=True, kw_only=True)
class RigCalibration:
    sensors: tuple[SensorCalibration, ...]
    resolution: Resolution = Resolution.HD1200
    world_frame: str = "floor"
    quality: dict[str, Any] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [s.name for s in self.sensors]
        if len(set(names)) != len(names):
            raise CalibrationFileError(f"sensor names must be unique, got {names}")
        if not self.sensors:
            raise CalibrationFileError("a calibration needs at least one sensor")

    def sensor(self, camera_serial: int, side: str) -> SensorCalibration:
        for s in self.sensors:
            if s.camera_serial == camera_serial and s.side == side:
                return s
        known = ", ".join(s.name for s in self.sensors)
        raise CalibrationFileError(f"no sensor for camera {camera_serial} {side}; have {known}")

    @property
    def camera_serials(self) -> tuple[int, ...]:
        return tuple(dict.fromkeys(s.camera_serial for s in self.sensors))

    # -- TOML ------------------------------------------------------------------------------------
    def to_toml(self) -> str:
        lines = [
            f"# EgoSurg rig calibration, format {CALIBRATION_FORMAT_VERSION}",
            f"format_version = {CALIBRATION_FORMAT_VERSION}",
            f"resolution = {_v(self.resolution.value)}",
            f"world_frame = {_v(self.world_frame)}",
            'conventions = "metres; OpenCV camera axes; pose is world-to-camera: '
            'x_cam = R @ x_world + t"',
        ]
        meta = {"software_version": __version__, "written_unix_ns": time.time_ns(), **self.metadata}
        lines += [f"{k} = {_v(v)}" for k, v in meta.items()]
        if self.quality:
            lines += ["", "[quality]", *[f"{k} = {_v(v)}" for k, v in self.quality.items()]]
        for s in self.sensors:
            lines += [
                "",
                "[[sensors]]",
                f"name = {_v(s.name)}",
                f"camera_serial = {s.camera_serial}",
                f"side = {_v(s.side)}",
                *camera_lines(s.intrinsics, s.pose, dist=True),
            ]
            if s.stats:
                lines += ["", "[sensors.stats]", *[f"{k} = {_v(v)}" for k, v in s.stats.items()]]
        return "\n".join(lines) + "\n"

    def write(self, path: Path | str) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.to_toml())
        return p

    @classmethod
    def read(cls, path: Path | str) -> RigCalibration:
        p = Path(path)
        try:
            text = p.read_text()
        except FileNotFoundError:
            raise CalibrationFileError(
                f"{p}: no such calibration file; make one with 'egosurg calibrate'"
            ) from None
        return cls.from_toml(text, str(p))

    @classmethod
    def from_toml(cls, text: str, source: str = "<calibration>") -> RigCalibration:
        data = parse_toml(text, source, error=CalibrationFileError)
        version = data.get("format_version")
        if version != CALIBRATION_FORMAT_VERSION:
            raise CalibrationFileError(
                f"{source}: format_version {version!r} is not supported (this reads "
                f"{CALIBRATION_FORMAT_VERSION}); recalibrate or upgrade EgoSurg"
            )
        try:
            res = Resolution.parse(data.get("resolution", "HD1200"))
            sensors = []
            for k, t in enumerate(data.get("sensors", [])):
                where = f"{source} [[sensors]] #{k + 1}"
                intrinsics, pose = read_camera(t, where, CalibrationFileError, dist=True)
                sensors.append(
                    SensorCalibration(
                        name=str(t["name"]),
                        camera_serial=int(t["camera_serial"]),
                        side=str(t["side"]),
                        intrinsics=intrinsics,
                        pose=pose,
                        stats={str(a): b for a, b in t.get("stats", {}).items()},
                    )
                )
        except KeyError as exc:
            raise CalibrationFileError(f"{source}: a sensor lacks {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            if isinstance(exc, UserError):
                raise
            raise CalibrationFileError(f"{source}: {exc}") from None
        skip = {"format_version", "resolution", "world_frame", "conventions", "quality", "sensors"}
        return cls(
            sensors=tuple(sensors),
            resolution=res,
            world_frame=str(data.get("world_frame", "floor")),
            quality=dict(data.get("quality", {})),
            metadata={k: v for k, v in data.items() if k not in skip},
        )
