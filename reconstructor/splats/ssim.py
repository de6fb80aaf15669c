"""SSIM and L1 as the training loss and the metrics use them, on (H, W, 3) float images in [0, 1].

SSIM follows Wang et al. (2004) as the 3DGS code computes it: an 11x11 Gaussian window with
sigma 1.5, constants C1 = 0.01², C2 = 0.03², averaged over channels and pixels. The window is
applied separably (two 1-D convolutions), which is the same maths at a fraction of the cost.
The training loss uses ``1 - ssim`` ("D-SSIM"). A mask (H, W) restricts both metrics to the
pixels that hold an image (undistortion leaves a thin invalid border). The scores that only
evaluation reports (PSNR, SSIM as a number) are in ``reconstructor/evaluation/metrics.py``.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
import torch
import torch.nn.functional as F

SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@functools.lru_cache(maxsize=4)
def gauss_1d(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def blur_reference(x: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W) with zero padding (3DGS's conv2d), by torch's
    grouped convolution: the slow, obvious twin of ``blur``."""
    g = gauss_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX).to(x.device, x.dtype)
    c = x.shape[1]
    pad = SSIM_WINDOW_PX // 2
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, pad), groups=c)
    return F.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(pad, 0), groups=c)


def _blur_hwc(x: np.ndarray) -> np.ndarray:
    """OpenCV's separable filter on (H, W, C) float32, zero borders, all channels at once."""
    g = gauss_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX).numpy().astype(np.float32)
    return cv2.sepFilter2D(x, -1, g, g, borderType=cv2.BORDER_CONSTANT)


class _BlurHWC(torch.autograd.Function):
    """The same blur through OpenCV on (H, W, C) images, 10x faster than ``blur_reference``.

    Zero-padded convolution with a symmetric kernel is self-adjoint: the backward pass is the
    same blur of the incoming gradient.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(_blur_hwc(np.ascontiguousarray(x.detach().numpy())))

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(_blur_hwc(np.ascontiguousarray(grad.detach().numpy())))


def blur(x: torch.Tensor) -> torch.Tensor:
    """SSIM's Gaussian window over (H, W, C) float32 (channels last), differentiable; off the
    CPU (a GPU), torch's convolution on that device."""
    if x.dtype != torch.float32 or x.shape[2] > 512 or x.device.type != "cpu":
        return blur_reference(x.permute(2, 0, 1)[None])[0].permute(1, 2, 0)
    return _BlurHWC.apply(x)


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (H, W), averaged over channels, of two (H, W, 3) images in [0, 1]."""
    c = a.shape[2]
    stack = blur(torch.cat([a, b, a * a, b * b, a * b], dim=2))
    mu_x, mu_y, xx, yy, xy = stack.split(c, dim=2)
    mu_xy = mu_x * mu_y
    mu_x2, mu_y2 = mu_x * mu_x, mu_y * mu_y
    num = (2 * mu_xy + SSIM_C1) * (2 * (xy - mu_xy) + SSIM_C2)
    den = (mu_x2 + mu_y2 + SSIM_C1) * (xx - mu_x2 + yy - mu_y2 + SSIM_C2)
    return (num / den).mean(dim=2)


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of two (H, W, 3) images, over ``mask`` (H, W) when given."""
    m = ssim_map(a, b)
    if mask is None:
        return m.mean()
    return (m * mask).sum() / mask.sum().clamp_min(1.0)


def l1(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error of two (H, W, 3) images, over ``mask`` (H, W) when given."""
    d = (a - b).abs().mean(dim=2)
    if mask is None:
        return d.mean()
    return (d * mask).sum() / mask.sum().clamp_min(1.0)
