"""A camera (intrinsics and world-to-camera pose) as a TOML table, read and written one way.

The rig calibration's ``[[sensors]]`` and the evaluation set's ``[[scenes.views]]`` hold the same
keys, so both files read and write them here::

    width_px = 960
    height_px = 600
    fx_px = 480.0
    fy_px = 480.0
    cx_px = 479.5
    cy_px = 299.5
    dist = [0.0, 0.0, 0.0, 0.0, 0.0]      # only where the camera has a lens model (sensors);
                                          # 8 terms for OpenCV's rational model
    rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]   # world-to-camera
    translation_m = [0.0, 0.0, 0.0]

Poses are metres, OpenCV axes, ``x_cam = R @ x_world + t``. Floats are written with full
precision (``toml_value``), so a written camera reads back bit for bit.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from protocol.camera import Intrinsics, Pose


def read_camera(
    table: dict[str, Any], where: str, error: type[Exception], *, dist: bool
) -> tuple[Intrinsics, Pose]:
    """The intrinsics and pose in ``table``; ``error`` naming ``where`` for a bad pose.

    ``dist``: read the ``dist`` key (the lens's distortion); without it the camera is an ideal
    pinhole. A missing key raises ``KeyError`` with its name, and a value of the wrong type
    ``TypeError`` or ``ValueError``: the caller turns those into its own file's message.
    """
    R = np.asarray(table["rotation"], dtype=np.float64)
    t = np.asarray(table["translation_m"], dtype=np.float64)
    if R.shape != (3, 3) or t.shape != (3,):
        raise error(f"{where}: rotation must be 3x3 and translation_m 3 long")
    try:
        pose = Pose(R=R, t_m=t)
    except ValueError as exc:
        raise error(f"{where}: {exc}") from None
    extra: dict[str, Any] = {}
    if dist:
        extra["dist"] = tuple(float(d) for d in table["dist"])
    intrinsics = Intrinsics(
        width_px=int(table["width_px"]),
        height_px=int(table["height_px"]),
        fx_px=float(table["fx_px"]),
        fy_px=float(table["fy_px"]),
        cx_px=float(table["cx_px"]),
        cy_px=float(table["cy_px"]),
        **extra,
    )
    return intrinsics, pose


def camera_lines(intrinsics: Intrinsics, pose: Pose, *, dist: bool) -> list[str]:
    """The ``key = value`` lines ``read_camera`` reads (``dist`` only when asked)."""
    i = intrinsics
    lines = [
        f"width_px = {i.width_px}",
        f"height_px = {i.height_px}",
        f"fx_px = {toml_value(i.fx_px)}",
        f"fy_px = {toml_value(i.fy_px)}",
        f"cx_px = {toml_value(i.cx_px)}",
        f"cy_px = {toml_value(i.cy_px)}",
    ]
    if dist:
        lines.append(f"dist = {toml_value(list(i.dist))}")
    lines += [
        f"rotation = {toml_value([list(r) for r in pose.R])}",
        f"translation_m = {toml_value(list(pose.t_m))}",
    ]
    return lines


def toml_value(value: Any) -> str:
    """A TOML value with full float precision."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        f = float(value)
        if math.isnan(f) or math.isinf(f):
            return "nan" if math.isnan(f) else ("inf" if f > 0 else "-inf")
        return repr(f)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list | tuple | np.ndarray):
        return "[" + ", ".join(toml_value(x) for x in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")
