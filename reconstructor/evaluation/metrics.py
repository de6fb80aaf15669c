"""Image scores as evaluation reports them: PSNR (dB) and SSIM as plain floats, on (H, W, 3)
images in [0, 1] (uint8 images are scaled by 1/255), optionally inside a (H, W) valid-pixel mask.

SSIM is the training loss's own (``reconstructor/splats/ssim.py``: 3DGS's 11 x 11 Gaussian
window, sigma 1.5), so a score and the loss can never drift apart.
"""

from __future__ import annotations

import numpy as np
import torch

from reconstructor.splats.ssim import ssim


def psnr(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray, mask=None) -> float:
    """PSNR in dB of two (H, W, 3) images in [0, 1] (uint8 images are scaled by 1/255)."""
    ta, tb = _as_float(a), _as_float(b)
    se = ((ta - tb) ** 2).mean(dim=2)
    if mask is None:
        mse = se.mean()
    else:
        tm = torch.as_tensor(np.asarray(mask) if not torch.is_tensor(mask) else mask).float()
        mse = (se * tm).sum() / tm.sum().clamp_min(1.0)
    return float(10 * torch.log10(1.0 / mse.clamp_min(1e-12)))


def ssim_value(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray, mask=None) -> float:
    """SSIM of two images as a float; accepts uint8 or float arrays or tensors."""
    tm = None if mask is None else torch.as_tensor(np.asarray(mask)).float()
    with torch.no_grad():
        return float(ssim(_as_float(a), _as_float(b), tm))


def _as_float(x: torch.Tensor | np.ndarray) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x.detach())
    if t.dtype == torch.uint8:
        return t.float() / 255.0
    return t.float()
