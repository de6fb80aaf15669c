"""``rasterize()``: render 3D Gaussians on the CPU, differentiably (the numba fast path).

Conventions:
    * Camera axes are OpenCV's: x right, y down, z forward; ``viewmat`` maps world to camera.
    * Pixel centres: pixel (u, v) (column u, row v, integer indices) has its centre at the
      continuous image point (u, v), as OpenCV's K (cx, cy in pixel-index coordinates). The
      image covers [-0.5, W - 0.5] x [-0.5, H - 0.5].
    * Tiles are ``tile_px`` squares from pixel (0, 0); the last row/column may be partial.

Maths (standard 3DGS, Kerbl et al. 2023). Projection (``projection.py``): each Gaussian gives
mean2d, conic = (Σ2D + eps2d I)⁻¹, its camera depth z and radius = ceil(sigma_extent ·
sqrt(λ_max)); it is culled (radius 0) if z ∉ [near_m, far_m] or its square mean2d ± radius
holds no pixel centre. Binning: it is listed in every tile holding a pixel centre of that
square where its alpha can reach alpha_min (none if its opacity is below alpha_min: leaving
out tiles it cannot draw in changes no output and halves a trained model's tile lists); each
tile's list is sorted front to back by z (ties by index). Compositing, per pixel
p, over its tile's list in order:

    α_i = min(alpha_max, opacity_i · exp(-½ dᵢᵀ conic_i dᵢ)),  dᵢ = p - mean2d_i
    skip the fragment if α_i < alpha_min
    stop (without this fragment) if T · (1 - α_i) < transmittance_min
    C += c_i α_i T;  D += z_i α_i T;  T *= (1 - α_i)          (T starts at 1)
    image = C + T · background,  alpha = 1 - T,  depth = D / alpha (0 where alpha < 1e-3)

Differentiable outputs: ``image`` and ``alpha``, to means_m, quats_wxyz, log_scales,
opacity_logits, colors and background (``alpha`` does not depend on colors/background).
``depth_m`` and ``radii_px`` carry no gradient. The clamp ``α = alpha_max`` passes no gradient
(as autograd's clamp); skipped fragments and culled Gaussians get exactly zero.

The backward pass is written out: ``kernels.raster_backward`` (pixel → per-Gaussian screen
gradients) then ``projection.project_backward`` (screen → world parameters). When no gradient
can follow (grad mode off, or no differentiable input requires grad), ``rasterize`` skips
autograd and the forward's bookkeeping for the backward (``kernels.raster_render``); its
outputs are bit for bit those of the training forward.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from reconstructor.raster import kernels, projection
from reconstructor.raster.config import RasterConfig, RenderInputs, RenderOutput

logger = logging.getLogger(__name__)

_DEFAULT_CONFIG = RasterConfig()
# Tiles differ a lot in cost (sky vs. clutter): hand them out a few at a time, not in halves.
_TILE_CHUNK = 4
_stage_ms: dict[str, float] = {}


def stage_times_ms() -> dict[str, float]:
    """Wall time of each stage of the last numba forward/backward, for profiling."""
    return dict(_stage_ms)


def rasterize(
    means_m: Tensor,
    quats_wxyz: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width_px: int,
    height_px: int,
    background: Tensor,
    config: RasterConfig = _DEFAULT_CONFIG,
) -> RenderOutput:
    """Render N Gaussians seen by a pinhole camera (CPU, float32).

    Args:
        means_m: (N, 3) world positions.
        quats_wxyz: (N, 4) rotations, any non-zero norm (normalised inside, differentiably).
        log_scales: (N, 3) log of the standard deviations along the Gaussian's axes, metres.
        opacity_logits: (N,) opacity = sigmoid(logit).
        colors: (N, 3) RGB (may exceed [0, 1]).
        viewmat: (4, 4) world-to-camera, OpenCV axes; no gradient.
        K: (3, 3) pinhole intrinsics, pixel-index centres (see module doc); no gradient.
        width_px, height_px: image size, > 0.
        background: (3,) RGB behind everything.
        config: culling, compositing and backend settings.

    Returns:
        RenderOutput(image (H, W, 3), alpha (H, W), depth_m (H, W), radii_px (N,) int32);
        image and alpha are differentiable, depth_m and radii_px are not.

    Raises:
        ValueError: naming the argument, for wrong shapes/dtypes/devices, non-finite values,
            zero quaternions or a non-positive image size or focal length.
    """
    on_gpu = config.backend == "gsplat"
    inputs = RenderInputs(
        means_m=means_m, quats_wxyz=quats_wxyz, log_scales=log_scales,
        opacity_logits=opacity_logits, colors=colors, viewmat=viewmat, K=K,
        width_px=width_px, height_px=height_px, background=background,
    )  # fmt: skip
    validate_inputs(inputs, any_device=on_gpu)
    if on_gpu:
        from reconstructor.raster.gsplat_backend import rasterize_gsplat

        return rasterize_gsplat(inputs, config)
    viewmat = viewmat.detach().to(torch.float64)
    K = K.detach().to(torch.float64)
    inputs = dataclasses.replace(inputs, viewmat=viewmat, K=K)
    if config.backend == "torch":
        from reconstructor.raster.reference import rasterize_reference

        return rasterize_reference(inputs, config)
    params = (means_m, quats_wxyz, log_scales, opacity_logits, colors, background)
    if not (torch.is_grad_enabled() and any(t.requires_grad for t in params)):
        return _render(inputs, config)
    image, alpha, depth, radii = _RasterizeFn.apply(
        *params, viewmat, K, width_px, height_px, config
    )
    return RenderOutput(image=image, alpha=alpha, depth_m=depth, radii_px=radii)


def validate_inputs(inputs: RenderInputs, *, any_device: bool = False) -> None:
    """Raise ValueError, naming the argument, unless the inputs are what ``rasterize`` takes.

    ``any_device`` (the gsplat backend): the Gaussians and the background may sit on any one
    device (viewmat and K anywhere); the value checks then cost one synchronisation."""
    for name in ("width_px", "height_px"):
        value = getattr(inputs, name)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    means_m, K = inputs.means_m, inputs.K
    n = means_m.shape[0] if isinstance(means_m, Tensor) and means_m.dim() == 2 else -1
    expected = {
        "means_m": ((n, 3), means_m),
        "quats_wxyz": ((n, 4), inputs.quats_wxyz),
        "log_scales": ((n, 3), inputs.log_scales),
        "opacity_logits": ((n,), inputs.opacity_logits),
        "colors": ((n, 3), inputs.colors),
        "background": ((3,), inputs.background),
        "viewmat": ((4, 4), inputs.viewmat),
        "K": ((3, 3), K),
    }
    for name, (shape, t) in expected.items():
        if not isinstance(t, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if tuple(t.shape) != shape or n < 0:
            want = "(N, 3)" if n < 0 else str(shape)
            raise ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")
        if name in ("viewmat", "K"):
            if not t.is_floating_point():
                raise ValueError(f"{name} must be a floating-point tensor, got {t.dtype}")
        elif t.dtype != torch.float32:
            raise ValueError(f"{name} must be float32, got {t.dtype}")
        if any_device:
            if name not in ("viewmat", "K") and t.device != means_m.device:
                raise ValueError(f"{name} is on {t.device}, the means on {means_m.device}")
        elif t.device.type != "cpu":
            raise ValueError(f"{name} must be on the CPU, got {t.device}")
    if any_device and means_m.device.type != "cpu":
        _check_values_on_device(expected, n)
    else:
        for name, (_, t) in expected.items():
            if not _all_finite(t.detach().cpu().numpy()):
                raise ValueError(f"{name} has non-finite values")
        if n > 0 and _min_sq_norm(_np32(inputs.quats_wxyz.cpu())) < 1e-24:
            raise ValueError("quats_wxyz has a zero quaternion; it cannot be normalised")
    if float(K[0, 0]) <= 0 or float(K[1, 1]) <= 0:
        raise ValueError(f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")


def _check_values_on_device(expected: dict[str, tuple[tuple[int, ...], Tensor]], n: int) -> None:
    """The finite and non-zero-quaternion checks on a GPU, read back in one synchronisation."""
    checks = [torch.isfinite(t.detach()).all() for _, t in expected.values()]
    if n > 0:
        q = expected["quats_wxyz"][1].detach()
        checks.append((q * q).sum(dim=1).min() >= 1e-24)
    ok = torch.stack([c.to(checks[0].device) for c in checks]).cpu().tolist()
    for name, good in zip(expected, ok, strict=False):
        if not good:
            raise ValueError(f"{name} has non-finite values")
    if n > 0 and not ok[-1]:
        raise ValueError("quats_wxyz has a zero quaternion; it cannot be normalised")


_PARALLEL_CHECK_MIN = 1 << 16  # below this many values numpy's serial check is quicker


def _all_finite(a: np.ndarray) -> bool:
    """No NaN or inf in a (any float dtype, any layout)."""
    if a.dtype == np.float32 and a.size >= _PARALLEL_CHECK_MIN and a.flags.c_contiguous:
        return _count_nonfinite(a.reshape(-1).view(np.uint32)) == 0
    # min/max propagate NaN and expose inf; 50x faster here than torch.isfinite().all()
    return not a.size or bool(np.isfinite(a.min()) and np.isfinite(a.max()))


@numba.njit(parallel=True, cache=True)
def _count_nonfinite(bits):
    """How many of the float32 values whose bits these are are inf or NaN (all exponent bits
    set): one parallel pass over the training inputs, where numpy's min and max took two
    serial ones (1 ms at 200k Gaussians)."""
    bad = 0
    for i in numba.prange(bits.shape[0]):
        bad += (bits[i] & 0x7F800000) == 0x7F800000
    return bad


@numba.njit(parallel=True, cache=True)
def _min_sq_norm(q):
    """Smallest squared norm of the rows of q (N, 4) float32, N > 0, summed in float32 like
    the ``np.einsum`` it replaces (a parallel pass instead of a serial one, 1 ms at 200k)."""
    smallest = np.float32(np.inf)
    for i in numba.prange(q.shape[0]):
        smallest = min(smallest, q[i, 0] * q[i, 0] + q[i, 1] * q[i, 1] + q[i, 2] * q[i, 2]
                       + q[i, 3] * q[i, 3])  # fmt: skip
    return float(smallest)


def _np32(t: Tensor) -> np.ndarray:
    """Zero-copy float32 numpy view of a CPU tensor (copies only if not contiguous)."""
    return t.detach().contiguous().numpy()


def _project_and_bin(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    logits: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    config: RasterConfig,
    with_slots: bool,
) -> tuple[projection.Projected, tuple[np.ndarray, ...], int]:
    """The stages before compositing, shared by the training forward and the render-only
    path: project, then bin (see ``kernels.bin_gaussians``; the render path needs no slots).
    Starts a new ``_stage_ms``.

    Returns: the projection, (pairs, offsets, slots, goffsets) and the tiles per row."""
    tile = config.tile_px
    ntx = -(-width // tile)
    nty = -(-height // tile)
    t0 = time.perf_counter()
    projected = projection.project(
        _np32(means), _np32(quats), _np32(log_scales), _np32(logits), _np32(colors),
        viewmat.numpy(), K.numpy(), width, height, tile, config.near_m, config.far_m,
        config.eps2d_px2, config.sigma_extent, config.alpha_min,
    )  # fmt: skip
    t1 = time.perf_counter()
    depth_bits = np.ascontiguousarray(projected.proj[:, projection.DEPTH]).view(np.uint32)
    binned = kernels.bin_gaussians(
        depth_bits, projected.radii, projected.rect, ntx, ntx * nty, numba.get_num_threads(),
        with_slots,
    )  # fmt: skip
    t2 = time.perf_counter()
    _stage_ms.clear()
    _stage_ms.update(project_fwd=1e3 * (t1 - t0), bin_sort=1e3 * (t2 - t1))
    return projected, binned, ntx


def _render(inputs: RenderInputs, config: RasterConfig) -> RenderOutput:
    """``rasterize`` when no gradient can follow: the training forward's image, alpha and depth
    bits, from ``kernels.raster_render``, which skips what only the backward pass needs."""
    width, height, background = inputs.width_px, inputs.height_px, inputs.background
    projected, (pairs, offsets, _, _), ntx = _project_and_bin(
        inputs.means_m, inputs.quats_wxyz, inputs.log_scales, inputs.opacity_logits,
        inputs.colors, inputs.viewmat, inputs.K, width, height, config, False,
    )  # fmt: skip
    t0 = time.perf_counter()
    with numba.parallel_chunksize(_TILE_CHUNK):
        image, t_final, depth = kernels.raster_render(
            projected.proj, pairs, offsets, width, height, config.tile_px, ntx,
            _np32(background), config.alpha_min, config.alpha_max, config.transmittance_min,
        )  # fmt: skip
    _stage_ms.update(raster_fwd=1e3 * (time.perf_counter() - t0))
    return RenderOutput(
        image=torch.from_numpy(image),
        alpha=torch.from_numpy(1.0 - t_final),
        depth_m=torch.from_numpy(depth),
        radii_px=torch.from_numpy(projected.radii),
    )


class _RasterizeFn(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx: Any,
        means: Tensor,
        quats: Tensor,
        log_scales: Tensor,
        logits: Tensor,
        colors: Tensor,
        background: Tensor,
        viewmat: Tensor,
        K: Tensor,
        width: int,
        height: int,
        config: RasterConfig,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        projected, (pairs, offsets, slots, goffsets), ntx = _project_and_bin(
            means, quats, log_scales, logits, colors, viewmat, K, width, height, config, True
        )
        bg = _np32(background)
        proj, radii, _, scales, opacity, intr, lims = projected
        vm = viewmat.numpy()
        tile = config.tile_px
        t0 = time.perf_counter()
        with numba.parallel_chunksize(_TILE_CHUNK):
            image, t_final, depth, n_used, drawn = kernels.raster_forward(
                proj, pairs, offsets, width, height, tile, ntx, bg,
                config.alpha_min, config.alpha_max, config.transmittance_min,
            )  # fmt: skip
        _stage_ms.update(raster_fwd=1e3 * (time.perf_counter() - t0))
        logger.debug(
            "rasterized %d Gaussians (%d visible, %d tile pairs) at %dx%d",
            means.shape[0], int((radii > 0).sum()), pairs.shape[0], width, height,
        )  # fmt: skip
        ctx.save_for_backward(means, quats)
        ctx.state = (
            proj, pairs, offsets, slots, goffsets, t_final, n_used, drawn, scales, opacity,
            intr, lims, vm, bg,
        )  # fmt: skip
        ctx.size = (width, height, tile, ntx)
        ctx.config = config
        radii_t = torch.from_numpy(radii)
        depth_t = torch.from_numpy(depth)
        ctx.mark_non_differentiable(depth_t, radii_t)
        return (
            torch.from_numpy(image),
            torch.from_numpy(1.0 - t_final),
            depth_t,
            radii_t,
        )

    @staticmethod
    def backward(
        ctx: Any, g_image: Tensor | None, g_alpha: Tensor | None, *_: Any
    ) -> tuple[Tensor | None, ...]:
        means, quats = ctx.saved_tensors
        (
            proj, pairs, offsets, slots, goffsets, t_final, n_used, drawn, scales, opacity,
            intr, lims, vm, bg,
        ) = ctx.state  # fmt: skip
        width, height, tile, ntx = ctx.size
        config: RasterConfig = ctx.config
        g_img = np.zeros((height, width, 3), np.float32) if g_image is None else _np32(g_image)
        g_a = np.zeros((height, width), np.float32) if g_alpha is None else _np32(g_alpha)
        t0 = time.perf_counter()
        with numba.parallel_chunksize(_TILE_CHUNK):
            records = kernels.raster_backward(
                proj, pairs, offsets, slots, width, height, tile, ntx, bg,
                config.alpha_min, config.alpha_max, t_final, n_used, drawn, g_img, g_a,
            )  # fmt: skip
        t1 = time.perf_counter()
        g_means, g_quats, g_log_scales, g_logits, g_colors = projection.project_backward(
            _np32(means), _np32(quats), scales, opacity, vm, intr, lims, config.eps2d_px2,
            records, goffsets,
        )  # fmt: skip
        t2 = time.perf_counter()
        g_bg = kernels.background_grad(t_final, g_img)  # dL/dbg = Σ_px T_final dL/dC
        _stage_ms.update(raster_bwd=1e3 * (t1 - t0), project_bwd=1e3 * (t2 - t1))
        return (
            torch.from_numpy(g_means),
            torch.from_numpy(g_quats),
            torch.from_numpy(g_log_scales),
            torch.from_numpy(g_logits),
            torch.from_numpy(g_colors),
            torch.from_numpy(g_bg),
            None,
            None,
            None,
            None,
            None,
        )
