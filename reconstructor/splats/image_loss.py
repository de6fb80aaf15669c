"""The training step's image loss, (1 - α) · L1 + α · (1 - SSIM), fused: value and gradient.

Same maths as ``metrics.l1`` and ``metrics.ssim`` under autograd (the slow, obvious twin,
``backend="torch"``), but each step's loss costs two passes over the image instead of about
forty torch operations forward and back, each allocating a full-size tensor
(``bench/bench_image_loss.py`` times both in one run). Each pass walks strips of rows in
parallel and keeps the blurred rows it needs in a ring of 11 rows, so no blurred plane is ever
written out: at 960x600 the loss and its gradient take about 30 ms on 2 cores, against 56 ms
when OpenCV blurred 24 whole planes (measured in one process).

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

import threading
import typing
from typing import Any, Literal

import numba
import numpy as np
import torch
from numba import njit, prange

from reconstructor.splats.ssim import (
    SSIM_C1,
    SSIM_C2,
    SSIM_SIGMA_PX,
    SSIM_WINDOW_PX,
    gauss_1d,
    l1,
    ssim,
)

LossBackend = Literal["numba", "torch"]
BACKENDS: tuple[LossBackend, ...] = typing.get_args(LossBackend)


def image_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    ssim_weight: float,
    fill: torch.Tensor | None = None,
    backend: LossBackend = "numba",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(1 - ssim_weight) · L1 + ssim_weight · (1 - SSIM) of two (H, W, 3) float32 images over
    ``mask`` (H, W); differentiable in ``rendered``.

    ``fill``: an RGB (3,) that stands in for the target where it has no content, i.e. the
    target compared is ``target · mask + fill · (1 - mask)`` (the trainer passes its random
    background). Returns (loss, l1, ssim); l1 and ssim are detached, for logging.
    ``backend="torch"`` is the twin: ``metrics.l1`` and ``metrics.ssim`` under autograd; it
    is also what runs on a GPU (the fused kernels are for the CPU), on the images' device.
    """
    if backend not in BACKENDS:
        raise ValueError(f"image_loss backend must be one of {BACKENDS}, got {backend!r}")
    cpu = rendered.device.type == "cpu"
    if backend == "torch" or not cpu or rendered.shape[2] != 3 or rendered.dtype != torch.float32:
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

    Two passes, each over strips of rows in parallel: ``_ssim_rows`` (the moments, their
    blur, SSIM and the d-maps) and ``_grad_rows`` (the d-maps' blur and the gradient). The
    blurred planes live only in a ring of 11 rows per strip; of the intermediate planes only
    the d-maps reach memory."""
    h, w, _ = x.shape
    mask_sum = max(float(mask.sum(dtype=np.float64)), 1.0)
    inv_norm = np.float32(1.0 / (3.0 * mask_sum))
    has_fill = fill is not None
    fill_rgb = np.ascontiguousarray(fill, np.float32) if has_fill else np.zeros(3, np.float32)
    n_strips = _n_strips(h)
    d_maps = _d_maps(h, w) if want_grad else np.empty((3, 1, 1), np.float32)
    rows = np.empty((2, h), np.float64)
    g = _window()
    _ssim_rows(x, y, mask, fill_rgb, has_fill, g, inv_norm, want_grad, n_strips, d_maps, rows)
    l1_v = float(rows[0].sum()) / mask_sum / 3.0
    ssim_v = float(rows[1].sum()) / mask_sum / 3.0
    if not want_grad:
        return l1_v, ssim_v, None
    grad = np.empty_like(x)
    alpha = np.float32(ssim_weight)
    _grad_rows(x, y, mask, fill_rgb, has_fill, g, inv_norm, alpha, n_strips, d_maps, grad)
    return l1_v, ssim_v, grad


_WIN = SSIM_WINDOW_PX  # a compile-time constant in the kernels: the tap loops unroll
_RAD = SSIM_WINDOW_PX // 2
_CH = 3  # channels, interleaved in a row as in the (H, W, 3) images: a row is 3 W floats
_STRIP_MIN_ROWS = 32  # each strip blurs 2 * _RAD rows beyond its own: keep that a small share


def _window() -> np.ndarray:
    """``metrics.blur``'s 1-D window, float32 (11,)."""
    return gauss_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX).numpy().astype(np.float32)


def _n_strips(h: int) -> int:
    """Strips of rows for the kernels: a few per thread, none under _STRIP_MIN_ROWS rows.
    Each row's result is computed the same way whatever the strips, so the number does not
    change a bit of the output."""
    return max(1, min(h // _STRIP_MIN_ROWS, 4 * numba.get_num_threads()))


_local = threading.local()


def _d_maps(h: int, w: int) -> np.ndarray:
    """The d-maps' (3, H, 3 W) buffer for one image size, kept between steps (per thread):
    allocating 20 MB afresh each step costs this VM more in page faults than the work."""
    d_maps = getattr(_local, "d_maps", None)
    if d_maps is None or d_maps.shape[1:] != (h, _CH * w):
        d_maps = np.empty((3, h, _CH * w), np.float32)
        _local.d_maps = d_maps
    return d_maps


@njit(cache=True, fastmath=True, error_model="numpy", inline="always")
def _blur_row(src, g, out):
    """out[i] = Σ_k g[k] src[i + 3 k]: the window along one row of interleaved channels,
    ``src`` padded with _RAD zero pixels on each side (zero borders, as ``metrics.blur``)."""
    for i in range(out.shape[0]):
        s = np.float32(0.0)
        for k in range(_WIN):
            s += g[k] * src[i + _CH * k]
        out[i] = s


@njit(cache=True, fastmath=True, error_model="numpy", inline="always")
def _blur_column(ring, g, first, out):
    """out[q, i] = Σ_k g[k] ring[q, (first + k) % _WIN, i]: the window down the ring's rows,
    the oldest (row v - _RAD of output row v) in slot ``first``."""
    nq, n = out.shape
    for q in range(nq):
        for i in range(n):
            out[q, i] = np.float32(0.0)
        for k in range(_WIN):
            gk = g[k]
            slot = (first + k) % _WIN
            for i in range(n):
                out[q, i] += gk * ring[q, slot, i]


@njit(cache=True, fastmath=True, error_model="numpy", inline="always")
def _row_target(x, y, mask, fill, has_fill, v, xr, yr, mr):
    """Row v as flat interleaved rows (3 W,): xr = x, yr = the target compared (y, filled
    with ``fill`` where the mask is not 1 if ``has_fill``), mr = the pixel's mask."""
    w = mask.shape[1]
    one = np.float32(1.0)
    for u in range(w):
        m = mask[v, u]
        for c in range(_CH):
            i = _CH * u + c
            b = y[v, u, c]
            if has_fill:
                b = b * m + fill[c] * (one - m)
            xr[i], yr[i], mr[i] = x[v, u, c], b, m


@njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _ssim_rows(x, y, mask, fill, has_fill, g, inv_norm, want_grad, n_strips, d_maps, rows):
    """Per image row: rows[0] = Σ mask · |x - y| and rows[1] = Σ mask · S over pixels and
    channels (float64), and, if ``want_grad``, d_maps (3, H, 3 W) = w ∂S/∂μx, w ∂S/∂E[x²],
    w ∂S/∂E[xy] (channels interleaved).

    Each strip of rows walks its rows plus _RAD above and below: the five moments of a row
    (x, y, x², y², xy), blurred along the row into a ring of _WIN rows; once the ring holds
    an output row's window, the column blur and SSIM of that row. All loops run along flat
    rows of interleaved channels, so they vectorise."""
    h, w = mask.shape
    n = _CH * w
    c1, c2 = np.float32(SSIM_C1), np.float32(SSIM_C2)
    one, two = np.float32(1.0), np.float32(2.0)
    size = (h + n_strips - 1) // n_strips
    for s in prange(n_strips):
        v0, v1 = s * size, min(h, (s + 1) * size)
        pad = np.zeros((5, n + 2 * _CH * _RAD), np.float32)  # the pads stay zero
        ring = np.empty((5, _WIN, n), np.float32)
        mu = np.empty((5, n), np.float32)  # μx, μy, E[x²], E[y²], E[xy] of one output row
        xr, yr, mr = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
        for vin in range(v0 - _RAD, v1 + _RAD):
            slot = (vin - v0 + _RAD) % _WIN
            if vin >= 0 and vin < h:
                _row_target(x, y, mask, fill, has_fill, vin, xr, yr, mr)
                o = _CH * _RAD
                for i in range(n):
                    a, b = xr[i], yr[i]
                    pad[0, o + i], pad[1, o + i], pad[2, o + i] = a, b, a * a
                    pad[3, o + i], pad[4, o + i] = b * b, a * b
                for q in range(5):
                    _blur_row(pad[q], g, ring[q, slot])
            else:
                for q in range(5):
                    for i in range(n):
                        ring[q, slot, i] = np.float32(0.0)
            v = vin - _RAD
            if v < v0:
                continue
            _blur_column(ring, g, (v - v0) % _WIN, mu)
            _row_target(x, y, mask, fill, has_fill, v, xr, yr, mr)
            acc_l1 = 0.0
            acc_s = 0.0
            for i in range(n):
                m = mr[i]
                mu_x, mu_y = mu[0, i], mu[1, i]
                a1 = two * mu_x * mu_y + c1
                a2 = two * (mu[4, i] - mu_x * mu_y) + c2
                b1 = mu_x * mu_x + mu_y * mu_y + c1
                b2 = mu[2, i] - mu_x * mu_x + mu[3, i] - mu_y * mu_y + c2
                inv_b1 = one / b1
                inv_b2 = one / b2
                s_px = a1 * a2 * inv_b1 * inv_b2
                acc_s += m * s_px
                acc_l1 += m * abs(xr[i] - yr[i])
                if want_grad:
                    wt = m * inv_norm
                    d_mu = two * (
                        mu_y * (a2 - a1) * inv_b1 * inv_b2 - mu_x * s_px * (inv_b1 - inv_b2)
                    )
                    d_maps[0, v, i] = wt * d_mu
                    d_maps[1, v, i] = -wt * s_px * inv_b2
                    d_maps[2, v, i] = wt * two * a1 * inv_b1 * inv_b2
            rows[0, v] = acc_l1
            rows[1, v] = acc_s


@njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _grad_rows(x, y, mask, fill, has_fill, g, inv_norm, alpha, n_strips, d_maps, grad):
    """grad (H, W, 3) = (1 - α) w sign(x - y) - α (G*d_μ + 2x G*d_xx + y G*d_xy): the d-maps
    blurred strip by strip through a ring of rows, as in ``_ssim_rows``."""
    h, w = mask.shape
    n = _CH * w
    one, zero, two = np.float32(1.0), np.float32(0.0), np.float32(2.0)
    l1_scale = inv_norm * (one - alpha)
    size = (h + n_strips - 1) // n_strips
    for s in prange(n_strips):
        v0, v1 = s * size, min(h, (s + 1) * size)
        pad = np.zeros((3, n + 2 * _CH * _RAD), np.float32)
        ring = np.empty((3, _WIN, n), np.float32)
        gd = np.empty((3, n), np.float32)  # G*d_μ, G*d_xx, G*d_xy of one output row
        xr, yr, mr = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
        for vin in range(v0 - _RAD, v1 + _RAD):
            slot = (vin - v0 + _RAD) % _WIN
            if vin >= 0 and vin < h:
                for q in range(3):
                    for i in range(n):
                        pad[q, _CH * _RAD + i] = d_maps[q, vin, i]
                    _blur_row(pad[q], g, ring[q, slot])
            else:
                for q in range(3):
                    for i in range(n):
                        ring[q, slot, i] = zero
            v = vin - _RAD
            if v < v0:
                continue
            _blur_column(ring, g, (v - v0) % _WIN, gd)
            _row_target(x, y, mask, fill, has_fill, v, xr, yr, mr)
            gr = grad[v].reshape(n)
            for i in range(n):
                xv, yv = xr[i], yr[i]
                sgn = np.float32(xv > yv) - np.float32(xv < yv)
                g_ssim = gd[0, i] + two * xv * gd[1, i] + yv * gd[2, i]
                gr[i] = mr[i] * l1_scale * sgn - alpha * g_ssim
