"""Rasterizer settings, inputs and outputs: :class:`RasterConfig` (validated on creation),
:class:`RenderInputs` (what each backend is handed) and :class:`RenderOutput`.

Units live in the names: ``_m`` metres (camera z), ``_px`` pixels, ``_px2`` squared pixels.
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass
from typing import Literal

from torch import Tensor

RasterBackend = Literal["numba", "torch", "gsplat"]
BACKENDS: tuple[RasterBackend, ...] = typing.get_args(RasterBackend)
# what gsplat's kernels compile in, for the settings that decide which fragments draw
GSPLAT_FIXED = {"alpha_min": 1 / 255, "transmittance_min": 1e-4}


@dataclass(frozen=True, kw_only=True)
class RasterConfig:
    """How :func:`reconstructor.raster.rasterize` culls, bins and composites.

    Attributes:
        tile_px: side of the square screen tiles Gaussians are binned into (1..32). 32, not
            3DGS's 16: on the CPU a Gaussian split over fewer tiles is gathered and visited
            fewer times, and a tile's state (32x32 pixels) still fits the L1/L2 caches; both
            compositing passes ran 1.2-1.3x faster than with 16 on a fresh and on a trained
            SVGA model (docs/history/benchmarks.md). Each pixel composites the same
            fragments in the same order whatever the tile; only rounding differs where a
            fragment sits right at alpha_min (a trained model: up to 4e-3 in a few pixels).
        near_m, far_m: Gaussians whose camera z lies outside ``[near_m, far_m]`` are culled.
        eps2d_px2: low-pass term added to the diagonal of every projected 2D covariance, so that
            even a point-like Gaussian covers about a pixel (3DGS uses 0.3).
        alpha_min: fragments with alpha below this are skipped (3DGS: 1/255).
        alpha_max: alpha is clamped to this (< 1: the backward pass divides by ``1 - alpha``).
        transmittance_min: a pixel stops compositing before the fragment that would drop its
            transmittance below this (3DGS: 1e-4).
        sigma_extent: screen radius of a Gaussian, in standard deviations of its major axis.
        backend: ``"numba"`` (the fast CPU kernels), ``"torch"`` (the slow autograd twin) or
            ``"gsplat"`` (gsplat's CUDA kernels, the ``gpu`` extra; ``--device cuda``). gsplat
            compiles in alpha_min = 1/255 and transmittance_min = 1e-4, so other values are
            refused with it; it clamps alpha at 0.999, not ``alpha_max``, and takes neither
            ``tile_px`` nor ``sigma_extent`` (``gsplat_backend.py`` maps each convention).
    """

    tile_px: int = 32
    near_m: float = 0.05
    far_m: float = 100.0
    eps2d_px2: float = 0.3
    alpha_min: float = 1 / 255
    alpha_max: float = 0.99
    transmittance_min: float = 1e-4
    sigma_extent: float = 3.0
    backend: RasterBackend = "numba"

    def __post_init__(self) -> None:
        if isinstance(self.tile_px, bool) or not isinstance(self.tile_px, int):
            raise ValueError(f"RasterConfig.tile_px must be an int, got {self.tile_px!r}")
        if not 1 <= self.tile_px <= 32:
            raise ValueError(f"RasterConfig.tile_px must be in [1, 32], got {self.tile_px}")
        for name in (
            "near_m",
            "far_m",
            "eps2d_px2",
            "alpha_min",
            "alpha_max",
            "transmittance_min",
            "sigma_extent",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"RasterConfig.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"RasterConfig.{name} must be finite, got {value}")
        if self.near_m <= 0:
            raise ValueError(f"RasterConfig.near_m must be > 0, got {self.near_m}")
        if self.far_m <= self.near_m:
            raise ValueError(
                f"RasterConfig.far_m must be > near_m ({self.near_m}), got {self.far_m}"
            )
        if self.eps2d_px2 < 0:
            raise ValueError(f"RasterConfig.eps2d_px2 must be >= 0, got {self.eps2d_px2}")
        if not 0 < self.alpha_min < 1:
            raise ValueError(f"RasterConfig.alpha_min must be in (0, 1), got {self.alpha_min}")
        if not self.alpha_min < self.alpha_max < 1:
            raise ValueError(
                f"RasterConfig.alpha_max must be in (alpha_min={self.alpha_min}, 1), "
                f"got {self.alpha_max}"
            )
        if not 0 <= self.transmittance_min < 1:
            raise ValueError(
                f"RasterConfig.transmittance_min must be in [0, 1), got {self.transmittance_min}"
            )
        if self.sigma_extent <= 0:
            raise ValueError(f"RasterConfig.sigma_extent must be > 0, got {self.sigma_extent}")
        if self.backend not in BACKENDS:
            raise ValueError(
                f"RasterConfig.backend must be one of {BACKENDS}, got {self.backend!r}"
            )
        if self.backend == "gsplat":
            for name, fixed in GSPLAT_FIXED.items():
                if not math.isclose(getattr(self, name), fixed, rel_tol=1e-6):
                    raise ValueError(
                        f"RasterConfig.{name}={getattr(self, name)!r}: gsplat compiles in "
                        f"{fixed!r}; use that value with backend 'gsplat', or another backend"
                    )

    @property
    def device(self) -> str:
        """Where this backend computes: ``"cuda"`` for gsplat, else ``"cpu"``."""
        return "cuda" if self.backend == "gsplat" else "cpu"


@dataclass(frozen=True, kw_only=True)
class RenderInputs:
    """One call's arguments of :func:`reconstructor.raster.rasterize`, as its backends receive
    them (checked by ``function.validate_inputs``; see ``rasterize`` for each one's meaning).

    Attributes:
        means_m: (N, 3); quats_wxyz: (N, 4); log_scales: (N, 3); opacity_logits: (N,);
            colors: (N, 3): the Gaussians, float32.
        viewmat: (4, 4) world-to-camera; K: (3, 3) pinhole intrinsics; no gradient.
        width_px, height_px: the image size.
        background: (3,) RGB behind everything.
    """

    means_m: Tensor
    quats_wxyz: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    colors: Tensor
    viewmat: Tensor
    K: Tensor
    width_px: int
    height_px: int
    background: Tensor


@dataclass(frozen=True)
class RenderOutput:
    """What :func:`reconstructor.raster.rasterize` returns (float32, on the CPU; with
    ``backend="gsplat"``, on the device of the Gaussians' means).

    Attributes:
        image: (H, W, 3) colour composited over the background; differentiable.
        alpha: (H, W) ``1 - final transmittance``; differentiable.
        depth_m: (H, W) alpha-weighted camera-z depth divided by alpha, 0 where alpha < 1e-3;
            forward only (no gradient).
        radii_px: (N,) int32 screen radius of each Gaussian, 0 where culled; no gradient.
    """

    image: Tensor
    alpha: Tensor
    depth_m: Tensor
    radii_px: Tensor
