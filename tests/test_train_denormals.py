"""The trainer flushes float32 denormals: the Adam moments of faded Gaussians decay into that
range, where every operation on them is many times slower (BENCHMARKS.md, "Reconstruction
schedule")."""

from __future__ import annotations

import numpy as np
import torch

from reconstructor.gaussians import init_from_points
from reconstructor.raster import RasterConfig
from reconstructor.train import TrainConfig, Trainer


def test_a_trainer_flushes_denormal_floats_to_zero() -> None:
    tiny = torch.tensor([1e-30], dtype=torch.float32)
    torch.set_flush_denormal(False)
    try:
        assert float(tiny * 1e-9) != 0.0  # a denormal, kept by default
        points = np.random.default_rng(0).uniform(-1, 1, size=(8, 3))
        gaussians = init_from_points(points, np.full((8, 3), 0.5))
        Trainer(gaussians, TrainConfig(), RasterConfig(), 1.0)
        assert float(tiny * 1e-9) == 0.0
    finally:
        torch.set_flush_denormal(False)
