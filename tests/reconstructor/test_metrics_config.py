"""Image metrics, the reconstructor's config file, and how --at picks a set."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import resolve_at
from reconstructor.errors import ReconstructConfigError, TimestampError
from reconstructor.evaluation.metrics import psnr, ssim_value


def _ssim_opencv(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM written independently with OpenCV's Gaussian blur and zero borders, per channel."""

    def blur(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x, (11, 11), 1.5, borderType=cv2.BORDER_CONSTANT)

    c1, c2 = 0.01**2, 0.03**2
    values = []
    for ch in range(3):
        x, y = a[:, :, ch].astype(np.float64), b[:, :, ch].astype(np.float64)
        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        values.append(s)
    return float(np.mean(values))


def test_psnr_of_a_known_error():
    a = np.zeros((20, 30, 3), np.float32)
    b = a + 0.1  # MSE 0.01 -> 20 dB
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    assert psnr(np.zeros((4, 4, 3), np.uint8), np.full((4, 4, 3), 255, np.uint8)) == 0.0


def test_psnr_mask_ignores_pixels_outside_it():
    a = np.zeros((10, 10, 3), np.float32)
    b = a.copy()
    b[:, :5] = 1.0
    mask = np.zeros((10, 10), bool)
    mask[:, 5:] = True
    assert psnr(a, b, mask) > 100


def test_ssim_matches_an_independent_opencv_computation():
    rng = np.random.default_rng(0)
    a = rng.random((48, 64, 3)).astype(np.float32)
    a = cv2.GaussianBlur(a, (5, 5), 1.0)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    assert ssim_value(a, b) == pytest.approx(_ssim_opencv(a, b), abs=1e-4)
    assert ssim_value(a, a) == pytest.approx(1.0, abs=1e-6)


def test_ssim_is_differentiable():
    from reconstructor.splats.ssim import ssim

    a = torch.rand(16, 16, 3, requires_grad=True)
    b = torch.rand(16, 16, 3)
    ssim(a, b).backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


def test_config_round_trips_through_its_toml():
    cfg = ReconstructConfig().resolved(960)
    again = ReconstructConfig.from_toml(cfg.to_toml())
    assert again == cfg


def test_config_overrides_and_bad_keys():
    cfg = ReconstructConfig.from_toml('train_views = "left"\n[train]\nwarmup_steps = 10\n')
    assert cfg.train_views == "left" and cfg.train.warmup_steps == 10
    assert cfg.train.refine_steps == ReconstructConfig().train.refine_steps
    with pytest.raises(ReconstructConfigError, match=r"train\.warmup_step"):
        ReconstructConfig.from_toml("[train]\nwarmup_step = 10\n")
    with pytest.raises(ReconstructConfigError, match="ssim_weight"):
        ReconstructConfig.from_toml("[train]\nssim_weight = 2.0\n")
    with pytest.raises(ReconstructConfigError, match="train_views"):
        ReconstructConfig.from_toml('train_views = "right"\n')
    with pytest.raises(ReconstructConfigError, match="not valid TOML"):
        ReconstructConfig.from_toml("[train\n")


def test_at_accepts_times_and_set_indices_and_names_the_valid_range():
    start = 1_000_000_000_000
    sets = start + np.arange(0, 150) * 66_666_667 + 20_000_000  # 15 fps, 10 s
    assert resolve_at("set:7", sets, start) == 7
    assert resolve_at("2.0", sets, start) == int(np.argmin(np.abs(sets - start - 2_000_000_000)))
    assert resolve_at("2s", sets, start) == resolve_at(2.0, sets, start)
    for bad in ("set:150", "60", "-3", "noon", "set:x"):
        with pytest.raises(TimestampError, match="set:0 to set:149"):
            resolve_at(bad, sets, start)


def test_fast_blur_matches_its_torch_twin_in_values_and_gradients():
    from reconstructor.splats.ssim import blur, blur_reference

    x = torch.rand(37, 53, 15, requires_grad=True)
    w = torch.rand(37, 53, 15)
    fast = blur(x)
    slow = blur_reference(x.permute(2, 0, 1)[None])[0].permute(1, 2, 0)
    assert torch.allclose(fast, slow, atol=1e-6)
    (gx_fast,) = torch.autograd.grad((fast * w).sum(), x)
    (gx_slow,) = torch.autograd.grad((slow * w).sum(), x)
    assert torch.allclose(gx_fast, gx_slow, atol=1e-6)
