"""Training on the GPU (gsplat backend) reaches what the CPU backend reaches, and its model is the
same kind of model: a short reconstruction of a sim timestamp (``tests/gpu_scene.py``) on both
backends, from the same Gaussians, with the same schedule, views, order and backgrounds.
Marked ``gpu``: it runs where CUDA and gsplat are.
"""

from __future__ import annotations

import statistics

import pytest
import torch

from reconstructor.errors import GpuUnavailableError
from reconstructor.evaluation.metrics import psnr
from reconstructor.raster import RasterConfig
from reconstructor.raster.gsplat_backend import require_gpu
from reconstructor.splats import ply
from reconstructor.splats.train import TrainConfig, Trainer, render

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]
STEPS = 300
PSNR_TOLERANCE_DB = 0.3  # the bound between the backends' evaluation numbers


@pytest.fixture(scope="module")
def scene():
    try:
        require_gpu()
    except GpuUnavailableError as e:
        pytest.skip(str(e))
    from tests.gpu_scene import scene_for_gpu

    return scene_for_gpu()[0]  # the sim's, or the file $EGOSURG_GPU_SCENE names


def _held_out_psnr(g, views, raster: RasterConfig) -> float:
    with torch.no_grad():
        return statistics.fmean(
            psnr(render(g, v, raster).image.clamp(0, 1), v.image, v.mask) for v in views
        )


def test_a_gpu_reconstruction_reaches_the_cpu_runs_psnr(scene, tmp_path) -> None:
    cfg = TrainConfig(warmup_steps=STEPS, refine_steps=0)
    models, losses = {}, {}
    for name, raster in (("cpu", RasterConfig()), ("cuda", RasterConfig(backend="gsplat"))):
        g = scene.gaussians.detach_clone()
        trainer = Trainer(g, cfg, raster, scene.extent_m)
        trainer.run(scene.train, STEPS)
        assert g.means_m.device.type == raster.device  # trained where the backend computes
        models[name], losses[name] = g, trainer.log.mean_loss(50)
    # the GPU model is an ordinary model: to the CPU, through a PLY, rendered by numba
    path = ply.write_ply(tmp_path / "gpu.ply", models["cuda"])
    back = ply.read_ply(path)
    cpu = _held_out_psnr(models["cpu"], scene.held_out, RasterConfig())
    gpu = _held_out_psnr(back, scene.held_out, RasterConfig())
    gpu_by_gsplat = _held_out_psnr(models["cuda"], scene.held_out, RasterConfig(backend="gsplat"))
    start = _held_out_psnr(scene.gaussians, scene.held_out, RasterConfig())
    print(
        f"held-out PSNR: start {start:.2f}, CPU {cpu:.2f}, GPU {gpu:.2f} dB (by gsplat "
        f"{gpu_by_gsplat:.2f}); loss CPU {losses['cpu']:.4f}, GPU {losses['cuda']:.4f}"
    )
    assert cpu > start + 0.5  # the schedule is long enough to learn something
    assert abs(gpu - cpu) <= PSNR_TOLERANCE_DB
    assert abs(gpu_by_gsplat - gpu) <= PSNR_TOLERANCE_DB


def test_views_go_to_the_gpu_once_per_run(scene) -> None:
    """The trainer copies each view to the GPU the first time it draws it, not every step."""
    g = scene.gaussians.detach_clone()
    trainer = Trainer(g, TrainConfig(warmup_steps=12, refine_steps=0),
                      RasterConfig(backend="gsplat"), scene.extent_m)  # fmt: skip
    trainer.run(scene.train, 12)
    cached = trainer._device_views
    assert len(cached) == len(scene.train)
    first = {k: dv.image.data_ptr() for k, dv in cached.items()}
    trainer.run(scene.train, 8)
    assert {k: dv.image.data_ptr() for k, dv in trainer._device_views.items()} == first
