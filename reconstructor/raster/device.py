"""``--device cpu|cuda``: which rasterizer backend a command runs, checked before any work.

``egosurg reconstruct`` takes its backend from the config (``[raster] backend``) unless
``--device`` is given; commands that read a finished model (render, replay, sightline,
evaluate) render on the CPU unless ``--device cuda`` is given, whatever backend made the model:
a case reconstructed on a GPU replays on a laptop.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Literal

from reconstructor.raster.config import GSPLAT_FIXED, RasterConfig

Device = Literal["cpu", "cuda"]
DEVICES: tuple[Device, ...] = typing.get_args(Device)


def add_device_option(parser: argparse.ArgumentParser, default: str = "the CPU") -> None:
    parser.add_argument(
        "--device",
        choices=DEVICES,
        help=f"cuda: gsplat's CUDA rasterizer (pip install 'egosurg[gpu]'); default: {default}",
    )


def for_device(raster: RasterConfig, device: str | None) -> RasterConfig:
    """``raster`` on ``device`` (None: as configured); for CUDA, first checks that the gsplat
    backend can run here (one-line ``GpuUnavailableError`` otherwise)."""
    if device is None:
        result = raster
    elif device == "cuda":
        result = dataclasses.replace(
            raster,
            backend="gsplat",
            alpha_min=GSPLAT_FIXED["alpha_min"],
            transmittance_min=GSPLAT_FIXED["transmittance_min"],
        )
    elif device == "cpu":
        result = dataclasses.replace(raster, backend="numba") if raster.device != "cpu" else raster
    else:
        raise ValueError(f"device must be one of {DEVICES}, got {device!r}")
    if result.device == "cuda":
        from reconstructor.raster.gsplat_backend import require_gpu

        require_gpu()
    return result


def check_device(device: str | None) -> None:
    """Fail now, in one line, if ``device`` cannot be used here: before a command's work."""
    if device is not None:
        for_device(RasterConfig(), device)
