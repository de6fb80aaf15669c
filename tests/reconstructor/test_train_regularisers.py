"""The trainer's regularisers beyond the image loss."""

from __future__ import annotations

import math

import pytest
import torch

from reconstructor.data.views import View
from reconstructor.errors import ReconstructConfigError
from reconstructor.raster import RasterConfig
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import TrainConfig, Trainer, anisotropy_penalty


def test_a_needle_pays_and_a_disc_does_not():
    scales = torch.tensor(
        [
            [0.10, 0.10, 0.001],  # a flat disc: a surface element, free
            [0.04, 0.01, 0.01],  # 4:1, at the limit
            [0.10, 0.01, 0.01],  # a needle, 10:1
        ]
    )
    each = [float(anisotropy_penalty(torch.log(s[None]), 4.0)) for s in scales]
    assert each[0] == 0.0 and each[1] == pytest.approx(0.0, abs=1e-6)
    assert each[2] == pytest.approx(math.log(10 / 4), rel=1e-5)


def _gaussians(log_scales: list[list[float]]) -> Gaussians:
    n = len(log_scales)
    return Gaussians(
        means_m=torch.tensor([[0.0, 0.0, 2.0]] * n),
        quats_wxyz=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        log_scales=torch.tensor(log_scales),
        opacity_logits=torch.zeros(n),
        sh_dc=torch.zeros(n, 3),
        sh_rest=torch.zeros(n, 0, 3),
    )


def _view_away_from_them() -> View:
    """A camera looking down -z from the origin: the Gaussians at z = +2 m are behind it, so the
    image loss gives them no gradient and only the regularisers move them."""
    viewmat = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
    K = torch.tensor([[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])
    return View("away", torch.full((24, 32, 3), 0.5), torch.ones(24, 32), viewmat, K, 32, 24)


@pytest.mark.parametrize("weight", [0.0, 0.5])
def test_the_anisotropy_term_shortens_needles_only_when_it_is_on(weight):
    needle = [math.log(0.2), math.log(0.01), math.log(0.01)]
    g = _gaussians([needle])
    cfg = TrainConfig(
        warmup_steps=30, refine_steps=0, anisotropy_reg_weight=weight, opacity_reg_weight=0.0
    )
    trainer = Trainer(g, cfg, RasterConfig(), extent_m=1.0)
    trainer.run([_view_away_from_them()], 30)
    ratio = float(torch.exp(g.log_scales[0, 0] - g.log_scales[0, 1]).detach())
    if weight == 0.0:
        assert ratio == pytest.approx(20.0, rel=1e-4)
    else:
        assert ratio < 20.0 * math.exp(-30 * 0.5 * cfg.scale_lr)  # Adam: about lr per step


def test_a_ratio_below_one_is_refused():
    with pytest.raises(ReconstructConfigError, match="anisotropy_max_ratio"):
        TrainConfig(anisotropy_max_ratio=0.5)
