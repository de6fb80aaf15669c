"""Tile-based differentiable 3D Gaussian splatting rasterizer for the CPU.

``rasterize()`` renders N Gaussians into an (H, W) image with gradients to every Gaussian
parameter and the background; ``RasterConfig(backend="torch")`` swaps the numba kernels for the
slow pure-PyTorch twin used to test them. See ``reconstructor.raster.function`` for the
conventions and the maths.
"""

from __future__ import annotations

from protocol.numba_threads import use_openmp_threads

use_openmp_threads()  # before any kernel of this package is compiled or launched

from reconstructor.raster.config import RasterConfig, RenderOutput  # noqa: E402
from reconstructor.raster.function import rasterize  # noqa: E402

__all__ = ["RasterConfig", "RenderOutput", "rasterize"]
