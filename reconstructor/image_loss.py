"""The training step's image loss, (1 - α) · L1 + α · (1 - SSIM), fused: value and gradient.

Same maths as ``metrics.l1`` and ``metrics.ssim`` under autograd (the slow, obvious twin,
``backend="torch"``), but each step's loss costs two blurs and three passes over the image
instead of about forty torch operations forward and back, each allocating a full-size tensor
(``bench/bench_image_loss.py`` times both in one run).

SSIM per pixel and channel, with μ, E the Gaussian-windowed means (``metrics.blur``) of the
render x and target y::

    S = A1 A2 / (B1 B2),   A1 = 2 μx μy + C1,   A2 = 2 (E[xy] - μx μy) + C2,
                           B1 = μx² + μy² + C1, B2 = E[x²] - μx² + E[y²] - μy² + C2

Its derivatives in the blurred quantities that depend on x::

    ∂S/∂μx    = 2 μy (A2 - A1) / (B1 B2) - 2 μx S (1/B1 - 1/B2)
    ∂S/∂E[x²] = -S / B2
    ∂S/∂E[xy] = 2 A1 / (B1 B2)

and, the blur being self-adjoint (symmetric kernel, zero padding), the gradient in x is::

    dSSIM/dx = G * (w ∂S/∂μx) + 2 x · G * (w ∂S/∂E[x²]) + y · G * (w ∂S/∂E[xy])

with w the pixel's weight in the mean: mask / (3 Σ mask). The L1 term's gradient is
w · sign(x - y) (0 where equal, as torch's ``abs``). The forward pass computes the gradient
at once (the target has none), and the backward pass scales it.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import cv2
import numpy as np
import torch
from numba import njit, prange

from reconstructor.metrics import _C1, _C2, SSIM_SIGMA_PX, SSIM_WINDOW_PX, _gauss_1d, l1, ssim

BACKENDS = ("numba", "torch")


def image_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    ssim_weight: float,
    fill: torch.Tensor | None = None,
    backend: str = "numba",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(1 - ssim_weight) · L1 + ssim_weight · (1 - SSIM) of two (H, W, 3) float32 images over
    ``mask`` (H, W); differentiable in ``rendered``.

    ``fill``: an RGB (3,) that stands in for the target where it has no content, i.e. the
    target compared is ``target · mask + fill · (1 - mask)`` (the trainer passes its random
    background). Returns (loss, l1, ssim); l1 and ssim are detached, for logging.
    ``backend="torch"`` is the twin: ``metrics.l1`` and ``metrics.ssim`` under autograd.
    """
    if backend not in BACKENDS:
        raise ValueError(f"image_loss backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "torch" or rendered.shape[2] != 3 or rendered.dtype != torch.float32:
        if fill is not None:
            target = target * mask[..., None] + fill * (1 - mask[..., None])
        l1_v = l1(rendered, target, mask)
        ssim_v = ssim(rendered, target, mask)
        loss = (1 - ssim_weight) * l1_v + ssim_weight * (1 - ssim_v)
        return loss, l1_v.detach(), ssim_v.detach()
    stats = torch.empty(2, dtype=torch.float64)
    fill_rgb = None if fill is None else fill.detach().numpy().astype(np.float32)
    loss = _FusedImageLoss.apply(rendered, target, mask, float(ssim_weight), fill_rgb, stats)
    return loss, stats[0].float(), stats[1].float()


class _FusedImageLoss(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx: Any,
        rendered: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor,
        ssim_weight: float,
        fill: np.ndarray | None,
        stats: torch.Tensor,
    ) -> torch.Tensor:
        x = _np32(rendered)
        y = _np32(target)
        m = _np32(mask)
        want_grad = ctx.needs_input_grad[0]
        l1_v, ssim_v, grad = loss_and_grad(x, y, m, ssim_weight, fill, want_grad)
        stats[0], stats[1] = l1_v, ssim_v
        ctx.grad = grad
        loss = (1 - ssim_weight) * l1_v + ssim_weight * (1 - ssim_v)
        return torch.tensor(loss, dtype=torch.float32)

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        grad = torch.from_numpy(ctx.grad).mul_(g)  # the forward's own array: scale in place
        ctx.grad = None
        return grad, None, None, None, None, None


def _np32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().numpy(), dtype=np.float32)


def loss_and_grad(
    x: np.ndarray,
    y: np.ndarray,
    mask: np.ndarray,
    ssim_weight: float,
    fill: np.ndarray | None = None,
    want_grad: bool = True,
) -> tuple[float, float, np.ndarray | None]:
    """L1, SSIM and (if ``want_grad``) d loss / d x of (H, W, 3) float32 images over ``mask``,
    the target being ``y · mask + fill · (1 - mask)`` if ``fill`` (3,) is given, else ``y``.

    Works on planes (one (H, W) array per quantity and channel): OpenCV blurs a plane faster
    than an interleaved stack, and the per-pixel loops then vectorise along the rows.
    """
    h, w, _ = x.shape
    mask_sum = max(float(mask.sum(dtype=np.float64)), 1.0)
    inv_norm = np.float32(1.0 / (3.0 * mask_sum))
    ws = _workspace(h, w)
    planes = ws["planes"]  # x, y, x², y², x·y; 3 channels each
    has_fill = fill is not None
    _moments(x, y, mask, fill if has_fill else np.zeros(3, np.float32), has_fill, planes)
    _blur_planes(planes, ws["blurred"])
    d_maps = ws["d_maps"] if want_grad else ws["d_maps"][:, :1, :1]
    row_l1, row_ssim = ws["rows"][0], ws["rows"][1]
    _ssim_terms(planes, mask, ws["blurred"], inv_norm, want_grad, d_maps, row_l1, row_ssim)
    l1_v = float(row_l1.sum()) / mask_sum / 3.0
    ssim_v = float(row_ssim.sum()) / mask_sum / 3.0
    if not want_grad:
        return l1_v, ssim_v, None
    grad = np.empty_like(x)
    blurred_d = ws["blurred"][:9]  # the forward's blurred planes are no longer needed
    _blur_planes(d_maps, blurred_d)
    _combine(planes, mask, blurred_d, inv_norm, np.float32(ssim_weight), grad)
    return l1_v, ssim_v, grad


_local = threading.local()


def _workspace(h: int, w: int) -> dict[str, np.ndarray]:
    """Scratch planes for one image size, kept between steps (per thread): allocating 60 MB
    afresh each step costs this VM more in page faults than the arithmetic."""
    ws = getattr(_local, "ws", None)
    if ws is None or ws["planes"].shape[1:] != (h, w):
        ws = {
            "planes": np.empty((15, h, w), np.float32),
            "blurred": np.empty((15, h, w), np.float32),
            "d_maps": np.empty((9, h, w), np.float32),
            "rows": np.empty((2, h), np.float64),
        }
        _local.ws = ws
    return ws


_pool_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None


def _blur_pool() -> ThreadPoolExecutor:
    """Threads that blur planes side by side, one per core (made once, on first use)."""
    global _pool
    with _pool_lock:
        if _pool is None:
            cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
            _pool = ThreadPoolExecutor(max(cores, 1), thread_name_prefix="ssim-blur")
        return _pool


def _blur_planes(planes: np.ndarray, out: np.ndarray) -> None:
    """``metrics.blur``'s window over each (H, W) plane of (K, H, W) float32, into ``out``.

    The planes are blurred side by side on a small thread pool (OpenCV releases the GIL):
    one ``sepFilter2D`` call gains nothing from OpenCV's own threads at this size, and the
    trainer turns those off (``train.opencv_single_threaded``); two planes at a time took the
    15 planes of a 960x600 step from 42 to 19 ms (measured). Each plane is blurred whole by
    one thread, so the result does not depend on the schedule."""
    g = _gauss_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX).numpy().astype(np.float32)

    def blur(k: int) -> None:
        cv2.sepFilter2D(planes[k], -1, g, g, dst=out[k], borderType=cv2.BORDER_CONSTANT)

    for _ in _blur_pool().map(blur, range(planes.shape[0])):
        pass


@njit(parallel=True, cache=True, fastmath=True)
def _moments(x, y, mask, fill, has_fill, out):
    """out (15, H, W) = planes of x, y, x², y², x·y (3 channels each) of (H, W, 3) images,
    y filled with ``fill`` where the mask is not 1 if ``has_fill``."""
    h, w = x.shape[0], x.shape[1]
    one = np.float32(1.0)
    for v in prange(h):
        for c in range(3):
            for u in range(w):
                a, b = x[v, u, c], y[v, u, c]
                if has_fill:
                    b = b * mask[v, u] + fill[c] * (one - mask[v, u])
                out[c, v, u] = a
                out[3 + c, v, u] = b
                out[6 + c, v, u] = a * a
                out[9 + c, v, u] = b * b
                out[12 + c, v, u] = a * b


@njit(parallel=True, cache=True, fastmath=True)
def _ssim_terms(planes, mask, blurred, inv_norm, want_grad, d_maps, row_l1, row_ssim):
    """Per row: Σ mask · |x - y| and Σ mask · S over channels (float64), and, if
    ``want_grad``, the planes d_maps (9, H, W) = w ∂S/∂μx, w ∂S/∂E[x²], w ∂S/∂E[xy]."""
    h, w = mask.shape
    c1, c2 = np.float32(_C1), np.float32(_C2)
    one, two = np.float32(1.0), np.float32(2.0)
    for v in prange(h):
        acc_l1 = 0.0
        acc_s = 0.0
        for c in range(3):
            for u in range(w):
                m = mask[v, u]
                mu_x = blurred[c, v, u]
                mu_y = blurred[3 + c, v, u]
                a1 = two * mu_x * mu_y + c1
                a2 = two * (blurred[12 + c, v, u] - mu_x * mu_y) + c2
                b1 = mu_x * mu_x + mu_y * mu_y + c1
                b2 = blurred[6 + c, v, u] - mu_x * mu_x + blurred[9 + c, v, u] - mu_y * mu_y + c2
                inv_b1 = one / b1
                inv_b2 = one / b2
                s = a1 * a2 * inv_b1 * inv_b2
                acc_s += m * s
                acc_l1 += m * abs(planes[c, v, u] - planes[3 + c, v, u])
                if want_grad:
                    wt = m * inv_norm
                    d_mu = two * (mu_y * (a2 - a1) * inv_b1 * inv_b2 - mu_x * s * (inv_b1 - inv_b2))
                    d_maps[c, v, u] = wt * d_mu
                    d_maps[3 + c, v, u] = -wt * s * inv_b2
                    d_maps[6 + c, v, u] = wt * two * a1 * inv_b1 * inv_b2
        row_l1[v] = acc_l1
        row_ssim[v] = acc_s


@njit(parallel=True, cache=True, fastmath=True)
def _combine(planes, mask, blurred_d, inv_norm, alpha, grad):
    """grad (H, W, 3) = (1 - α) w sign(x - y) - α (G*d_μ + 2x G*d_xx + y G*d_xy)."""
    h, w = mask.shape
    one, zero, two = np.float32(1.0), np.float32(0.0), np.float32(2.0)
    for v in prange(h):
        for c in range(3):
            for u in range(w):
                x, y = planes[c, v, u], planes[3 + c, v, u]
                d = x - y
                sgn = one if d > zero else (-one if d < zero else zero)
                g_ssim = (
                    blurred_d[c, v, u]
                    + two * x * blurred_d[3 + c, v, u]
                    + y * blurred_d[6 + c, v, u]
                )
                grad[v, u, c] = mask[v, u] * inv_norm * (one - alpha) * sgn - alpha * g_ssim
