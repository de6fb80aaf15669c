"""Tile-based differentiable 3D Gaussian splatting rasterizer for the CPU.

``rasterize()`` renders N Gaussians into an (H, W) image with gradients to every Gaussian
parameter and the background; ``RasterConfig(backend="torch")`` swaps the numba kernels for the
slow pure-PyTorch twin used to test them. See ``reconstructor.raster.function`` for the
conventions and the maths.
"""

from __future__ import annotations

import os

import numba

# Numba's default layer picks TBB when present, which clashes with the TBB torch/open3d load;
# OpenMP is safe next to them. Select it before any kernel of this package is compiled or
# launched; NUMBA_THREADING_LAYER still overrides.
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "omp"  # type: ignore[attr-defined]

from reconstructor.raster.config import RasterConfig, RenderOutput
from reconstructor.raster.function import rasterize

__all__ = ["RasterConfig", "RenderOutput", "rasterize"]
