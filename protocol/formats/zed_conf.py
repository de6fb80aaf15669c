"""Reader and writer for the ZED factory calibration file, ``SN<serial>.conf``.

The file is INI text. For a ZED X it holds, per sensor and resolution, a section
``[LEFT_CAM_<RES>]`` / ``[RIGHT_CAM_<RES>]`` with ``fx fy cx cy`` (px) and ``k1 k2 p1 p2 k3``,
where ``<RES>`` is ``FHD1200`` (1920x1200), ``FHD`` (1920x1080) or ``SVGA`` (960x600); and one
``[STEREO]`` section with ``Baseline``, ``TY``, ``TZ`` (mm) and, per resolution, ``RX_<RES>``,
``CV_<RES>``, ``RZ_<RES>``: the components of a Rodrigues vector in radians.

Stereo convention, checked by a round trip in the tests: with ``R = Rodrigues([RX, CV, RZ])`` and
``T = [-Baseline, TY, TZ]`` mm, a point in the left camera's frame maps to the right camera's frame
as ``x_right = R @ x_left + T`` (OpenCV ``stereoCalibrate``'s R, T). The right sensor therefore
sits ``Baseline`` mm to the right (+x) of the left one.

Lens model: five terms ``k1 k2 p1 p2 k3`` (OpenCV's Brown-Conrady), or the eight-term rational
model (``k1 k2 p1 p2 k3 k4 k5 k6``, OpenCV's ``CALIB_RATIONAL_MODEL``) that Stereolabs uses for
the ZED X where the file has it: either ``k4 k5 k6`` next to the five in a ``[<SIDE>_CAM_<RES>]``
section (that resolution only), or a complete ``[LEFT_DISTO]`` / ``[RIGHT_DISTO]`` section (all
resolutions of that sensor, as the SDK reads it; distortion acts on normalized coordinates, so it
does not change with the mode). A five-term file writes back as it was read; an eight-term sensor
is written with ``k4 k5 k6`` in its camera sections.

Sections and keys the ZED SDK writes that EgoSurg does not use (``[MISC]``, ...) are kept out of
the model but tolerated on reading. A missing ``FHD`` or ``SVGA`` section is derived from
``FHD1200`` as the ZED X does it: ``FHD`` is ``FHD1200`` with ``cy - 60`` (a centre crop), ``SVGA``
is ``FHD1200`` halved (2x2 binning).
"""

from __future__ import annotations

import configparser
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.camera import Intrinsics, Pose, Resolution
from protocol.errors import UserError

INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
# The rational model's extra terms, after k3 (OpenCV's order), and the whole rational table.
RATIONAL_KEYS = ("k4", "k5", "k6")
DISTO_KEYS = ("k1", "k2", "p1", "p2", "k3", *RATIONAL_KEYS)


class ConfFormatError(UserError, ValueError):
    """A ZED factory file that cannot be read; the message names the file, section and field."""


@dataclass(frozen=True, kw_only=True)
class StereoCalibration:
    """One ZED X at one resolution: both sensors' intrinsics and the left-to-right transform."""

    serial: int
    resolution: Resolution
    left: Intrinsics
    right: Intrinsics
    R_right_from_left: np.ndarray
    T_right_from_left_m: np.ndarray

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T_right_from_left_m))

    @property
    def right_from_left(self) -> Pose:
        return Pose(R=self.R_right_from_left, t_m=self.T_right_from_left_m)


@dataclass(frozen=True, kw_only=True)
class ZedFactoryCalibration:
    """The contents of one ``SN<serial>.conf`` that EgoSurg uses."""

    serial: int
    left: dict[Resolution, Intrinsics]
    right: dict[Resolution, Intrinsics]
    baseline_mm: float
    ty_mm: float
    tz_mm: float
    rodrigues_rad: dict[Resolution, tuple[float, float, float]]

    def stereo(self, resolution: Resolution | str) -> StereoCalibration:
        res = Resolution.parse(resolution)
        import cv2

        rvec = np.asarray(self.rodrigues_rad[res], dtype=np.float64)
        R, _ = cv2.Rodrigues(rvec)
        T = np.array([-self.baseline_mm, self.ty_mm, self.tz_mm]) / 1000.0
        return StereoCalibration(
            serial=self.serial,
            resolution=res,
            left=self.left[res],
            right=self.right[res],
            R_right_from_left=R,
            T_right_from_left_m=T,
        )

    @property
    def filename(self) -> str:
        return f"SN{self.serial}.conf"

    def to_text(self) -> str:
        """The file text, in the section order the ZED SDK writes."""
        lines: list[str] = []
        for side, table in (("LEFT", self.left), ("RIGHT", self.right)):
            for res in Resolution:
                intr = table[res]
                values = (intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px, *intr.dist)
                lines.append(f"[{side}_CAM_{res.conf_suffix}]")
                keys = (*INTRINSIC_KEYS, *RATIONAL_KEYS) if intr.is_rational else INTRINSIC_KEYS
                lines += [f"{k}={_fmt(v)}" for k, v in zip(keys, values, strict=True)]
                lines.append("")
        lines.append("[STEREO]")
        lines += [
            f"Baseline={_fmt(self.baseline_mm)}",
            f"TY={_fmt(self.ty_mm)}",
            f"TZ={_fmt(self.tz_mm)}",
        ]
        for axis, i in (("CV", 1), ("RX", 0), ("RZ", 2)):
            for res in Resolution:
                lines.append(f"{axis}_{res.conf_suffix}={_fmt(self.rodrigues_rad[res][i])}")
        lines += ["", "[MISC]", "Sensor_ID=1", ""]
        return "\n".join(lines)

    def write(self, directory: Path | str) -> Path:
        path = Path(directory) / self.filename
        path.write_text(self.to_text())
        return path

    @classmethod
    def read(cls, path: Path | str) -> ZedFactoryCalibration:
        p = Path(path)
        try:
            text = p.read_text()
        except FileNotFoundError:
            raise ConfFormatError(
                f"{p}: no such factory calibration file; copy SN<serial>.conf from the camera's "
                "ZED settings folder (/usr/local/zed/settings/)"
            ) from None
        except UnicodeDecodeError:
            raise ConfFormatError(f"{p}: not a text file; is this really a ZED .conf?") from None
        return cls.parse(text, serial=_serial_from_name(p.name), source=str(p))

    @classmethod
    def parse(
        cls, text: str, *, serial: int | None = None, source: str = "<conf text>"
    ) -> ZedFactoryCalibration:
        """Parse file text. ``serial`` usually comes from the file name ``SN<serial>.conf``."""
        parser = configparser.ConfigParser(interpolation=None, strict=False)
        parser.optionxform = str  # type: ignore[assignment,method-assign]  # keys are case-sensitive
        try:
            parser.read_string(text, source=source)
        except configparser.Error as exc:
            first = str(exc).splitlines()[0]
            raise ConfFormatError(
                f"{source}: not a valid ZED .conf (INI) file: {first}; re-copy it from the camera"
            ) from None
        if serial is None:
            serial = 0
        left: dict[Resolution, Intrinsics] = {}
        right: dict[Resolution, Intrinsics] = {}
        for side, table in (("LEFT", left), ("RIGHT", right)):
            disto = _read_disto(parser, f"{side}_DISTO", source)
            base = _read_intrinsics(parser, f"{side}_CAM_FHD1200", Resolution.HD1200, source, disto)
            if base is None:
                raise ConfFormatError(
                    f"{source}: section [{side}_CAM_FHD1200] is missing; this is not a ZED X "
                    "factory file (ZED X files carry FHD1200, FHD and SVGA sections)"
                )
            table[Resolution.HD1200] = base
            for res in (Resolution.HD1080, Resolution.SVGA):
                section = f"{side}_CAM_{res.conf_suffix}"
                read = _read_intrinsics(parser, section, res, source, disto)
                table[res] = read if read is not None else derive_intrinsics(base, res)
        if not parser.has_section("STEREO"):
            raise ConfFormatError(f"{source}: section [STEREO] is missing; re-copy the file")
        stereo = parser["STEREO"]
        baseline = _number(stereo, "Baseline", "STEREO", source)
        if not 1.0 < baseline < 1000.0:
            raise ConfFormatError(
                f"{source}: [STEREO] Baseline={baseline} is not a stereo baseline in millimetres"
            )
        ty = _number(stereo, "TY", "STEREO", source)
        tz = _number(stereo, "TZ", "STEREO", source)
        rod: dict[Resolution, tuple[float, float, float]] = {}
        for res in Resolution:
            suf = res.conf_suffix
            keys = (f"RX_{suf}", f"CV_{suf}", f"RZ_{suf}")
            if not any(k in stereo for k in keys) and res is not Resolution.HD1200:
                rod[res] = rod[Resolution.HD1200]
                continue
            rx, cv, rz = (_number(stereo, k, "STEREO", source) for k in keys)
            rod[res] = (rx, cv, rz)
        return cls(
            serial=serial,
            left=left,
            right=right,
            baseline_mm=baseline,
            ty_mm=ty,
            tz_mm=tz,
            rodrigues_rad=rod,
        )


def derive_intrinsics(hd1200: Intrinsics, res: Resolution) -> Intrinsics:
    """ZED X rule: HD1080 is a centre crop of HD1200 (cy - 60); SVGA is HD1200 binned 2x2."""
    width, height = res.size
    if res is Resolution.HD1200:
        return hd1200
    if res is Resolution.HD1080:
        return Intrinsics(
            width_px=width,
            height_px=height,
            fx_px=hd1200.fx_px,
            fy_px=hd1200.fy_px,
            cx_px=hd1200.cx_px,
            cy_px=hd1200.cy_px - 60.0,
            dist=hd1200.dist,
        )
    return Intrinsics(
        width_px=width,
        height_px=height,
        fx_px=hd1200.fx_px / 2,
        fy_px=hd1200.fy_px / 2,
        cx_px=hd1200.cx_px / 2,
        cy_px=hd1200.cy_px / 2,
        dist=hd1200.dist,
    )


def _read_disto(
    parser: configparser.ConfigParser, section: str, source: str
) -> tuple[float, ...] | None:
    """A complete ``[<SIDE>_DISTO]`` rational table, or None (absent or partial: the SDK then
    falls back to the camera sections' five terms, and so do we)."""
    if not parser.has_section(section) or not all(k in parser[section] for k in DISTO_KEYS):
        return None
    return tuple(_number(parser[section], k, section, source) for k in DISTO_KEYS)


def _read_intrinsics(
    parser: configparser.ConfigParser,
    section: str,
    res: Resolution,
    source: str,
    disto: tuple[float, ...] | None = None,
) -> Intrinsics | None:
    if not parser.has_section(section):
        return None
    sec = parser[section]
    vals = [_number(sec, k, section, source) for k in INTRINSIC_KEYS]
    if all(k in sec for k in RATIONAL_KEYS):
        vals += [_number(sec, k, section, source) for k in RATIONAL_KEYS]
    dist = disto if disto is not None else tuple(vals[4:])
    fx, fy, cx, cy = vals[:4]
    if fx <= 0 or fy <= 0:
        raise ConfFormatError(f"{source}: [{section}] focal lengths must be positive (fx={fx})")
    width, height = res.size
    if not (0 < cx < width and 0 < cy < height):
        raise ConfFormatError(
            f"{source}: [{section}] principal point ({cx}, {cy}) lies outside the "
            f"{width}x{height} image"
        )
    return Intrinsics(
        width_px=width,
        height_px=height,
        fx_px=fx,
        fy_px=fy,
        cx_px=cx,
        cy_px=cy,
        dist=dist,
    )


def _number(section: configparser.SectionProxy, key: str, name: str, source: str) -> float:
    if key not in section:
        raise ConfFormatError(f"{source}: [{name}] has no '{key}' entry; re-copy the file")
    raw = section[key]
    try:
        value = float(raw)
    except ValueError:
        raise ConfFormatError(f"{source}: [{name}] {key}={raw!r} is not a number") from None
    if not np.isfinite(value):
        raise ConfFormatError(f"{source}: [{name}] {key}={raw!r} is not a finite number")
    return value


def _serial_from_name(name: str) -> int | None:
    m = re.fullmatch(r"SN(\d+)\.conf", name)
    return int(m.group(1)) if m else None


def _fmt(v: float) -> str:
    return repr(float(v))
