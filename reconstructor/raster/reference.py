"""The slow, obvious PyTorch twin of the rasterizer; autograd provides its backward.

Same maths as the numba path (see ``reconstructor.raster.function``): same culling, frustum
clamp, low-pass, binning, depth order (stable, ties by index), alpha skip and clamp and early
termination, all in float32. It exists to test the fast path against, so it favours
plainness: the projection is a few batched tensor expressions, and each tile is a dense
(pixels x Gaussians) block whose transmittance is a cumulative product.

Two things keep it usable on a full frame (960x600, 200k Gaussians, within minutes) without
changing a single value: each tile is rendered under ``torch.utils.checkpoint`` (recomputed
in the backward pass, so memory stays at one tile), and a tile's list is cut after the last
Gaussian any of its pixels reaches before terminating.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from reconstructor.raster.config import RasterConfig, RenderInputs, RenderOutput

logger = logging.getLogger(__name__)

_ALPHA_DEPTH_MIN = 1e-3


def project_reference(
    means_m: Tensor,
    quats_wxyz: Tensor,
    log_scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width_px: int,
    height_px: int,
    config: RasterConfig,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Project N Gaussians (float32, differentiable).

    Returns:
        mean2d (N, 2), conic (N, 3) as (a, b, c) of [[a, b], [b, c]], depth (N,) camera z,
        radii (N,) int32 (0 = culled) and rect (N, 4) int64 inclusive tile (x0, x1, y0, y1).
        Entries of culled Gaussians are finite but meaningless.
    """
    vm = viewmat.to(torch.float32)
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    w_rot, t_w = vm[:3, :3], vm[:3, 3]
    q = quats_wxyz / quats_wxyz.norm(dim=1, keepdim=True)
    w, x, y, z = q.unbind(dim=1)
    rot_q = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=1,
    ).reshape(-1, 3, 3)  # fmt: skip
    m = rot_q * torch.exp(log_scales)[:, None, :]
    cov3d = m @ m.transpose(1, 2)
    t_cam = means_m @ w_rot.T + t_w
    cov_cam = w_rot @ cov3d @ w_rot.T
    tx, ty, tz = t_cam.unbind(dim=1)
    in_depth = (tz >= config.near_m) & (tz <= config.far_m)
    tz = torch.where(in_depth, tz, torch.ones_like(tz))  # keeps culled rows finite
    lim_x = (
        (cx + 0.5) / fx + 0.15 * width_px / fx,
        (width_px - 0.5 - cx) / fx + 0.15 * width_px / fx,
    )
    lim_y = (
        (cy + 0.5) / fy + 0.15 * height_px / fy,
        (height_px - 0.5 - cy) / fy + 0.15 * height_px / fy,
    )
    u_t = torch.clamp(tx / tz, -lim_x[0], lim_x[1])
    v_t = torch.clamp(ty / tz, -lim_y[0], lim_y[1])
    zero = torch.zeros_like(tz)
    jac = torch.stack(
        [fx / tz, zero, -fx * u_t / tz, zero, fy / tz, -fy * v_t / tz], dim=1
    ).reshape(-1, 2, 3)
    cov2d = jac @ cov_cam @ jac.transpose(1, 2)
    s00 = cov2d[:, 0, 0] + config.eps2d_px2
    s11 = cov2d[:, 1, 1] + config.eps2d_px2
    s01 = cov2d[:, 0, 1]
    det = s00 * s11 - s01 * s01
    ok_det = det > 0
    det = torch.where(ok_det, det, torch.ones_like(det))
    conic = torch.stack([s11 / det, -s01 / det, s00 / det], dim=1)
    mean2d = torch.stack([fx * tx / tz + cx, fy * ty / tz + cy], dim=1)
    with torch.no_grad():
        mid = 0.5 * (s00 + s11)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0))
        radius = torch.ceil(config.sigma_extent * torch.sqrt(lam))
        lo = torch.clamp(mean2d - radius[:, None], -1e7, 1e7)
        hi = torch.clamp(mean2d + radius[:, None], -1e7, 1e7)
        u0 = torch.ceil(lo[:, 0]).long().clamp(min=0)
        u1 = torch.floor(hi[:, 0]).long().clamp(max=width_px - 1)
        v0 = torch.ceil(lo[:, 1]).long().clamp(min=0)
        v1 = torch.floor(hi[:, 1]).long().clamp(max=height_px - 1)
        visible = in_depth & ok_det & (radius > 0) & (u0 <= u1) & (v0 <= v1)
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
        tile = config.tile_px
        rect = torch.stack([u0 // tile, u1 // tile, v0 // tile, v1 // tile], dim=1)
    return mean2d, conic, t_cam[:, 2], radii, rect


def _render_tile(
    pix: Tensor, mean2d: Tensor, conic: Tensor, opacity: Tensor, colors: Tensor, depth: Tensor,
    alpha_min: float, alpha_max: float, t_min: float,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """Composite K depth-sorted Gaussians over P pixels (P, 2): colour (P, 3), T (P,), D (P,)."""

    def alphas(k: int) -> Tensor:
        d = pix[:, None, :] - mean2d[None, :k, :]  # (P, k, 2)
        dx, dy = d[..., 0], d[..., 1]
        a, b, c = conic[:k, 0], conic[:k, 1], conic[:k, 2]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = torch.clamp(opacity[:k] * torch.exp(power), max=alpha_max)
        return torch.where(alpha >= alpha_min, alpha, torch.zeros_like(alpha))

    with torch.no_grad():
        alpha = alphas(mean2d.shape[0])
        keep = torch.cumprod(1 - alpha, dim=1) >= t_min  # a prefix of each pixel's list
        used = (keep & (alpha > 0)).any(dim=0).nonzero()
        k = int(used.max()) + 1 if used.numel() else 0
        keep = keep[:, :k]
    alpha = alphas(k) * keep
    t_incl = torch.cumprod(1 - alpha, dim=1)
    t_excl = torch.cat([torch.ones_like(alpha[:, :1]), t_incl[:, :-1]], dim=1)
    weight = alpha * t_excl
    t_final = t_incl[:, -1] if k else torch.ones_like(pix[:, 0])
    return weight @ colors[:k], t_final, weight.detach() @ depth[:k]


def rasterize_reference(inputs: RenderInputs, config: RasterConfig) -> RenderOutput:
    """Same contract as ``rasterize`` (inputs already validated, viewmat and K in float64);
    backward by autograd."""
    colors, background = inputs.colors, inputs.background
    width_px, height_px = inputs.width_px, inputs.height_px
    mean2d, conic, depth, radii, rect = project_reference(
        inputs.means_m, inputs.quats_wxyz, inputs.log_scales, inputs.viewmat, inputs.K,
        width_px, height_px, config,
    )  # fmt: skip
    opacity = torch.sigmoid(inputs.opacity_logits)
    tile = config.tile_px
    ntx, nty = math.ceil(width_px / tile), math.ceil(height_px / tile)
    with torch.no_grad():
        vis = torch.nonzero(radii > 0).squeeze(1)
        order = vis[torch.argsort(depth[vis], stable=True)]
        rect_o = rect[order]
        tile_ids: list[Tensor] = []
        for ty in range(nty):
            in_row = order[(rect_o[:, 2] <= ty) & (rect_o[:, 3] >= ty)]
            rect_row = rect[in_row]
            for tx in range(ntx):
                tile_ids.append(in_row[(rect_row[:, 0] <= tx) & (rect_row[:, 1] >= tx)])
        pair_ids = torch.cat(tile_ids) if tile_ids else order
    # One gather for all pairs, then split per tile: autograd collects the pieces in one node.
    per_pair = torch.cat(
        [mean2d[pair_ids], conic[pair_ids], opacity[pair_ids, None], colors[pair_ids]], dim=1
    )
    pieces = torch.split(per_pair, [int(ids.numel()) for ids in tile_ids])
    depth_pairs = depth.detach()[pair_ids].split([int(ids.numel()) for ids in tile_ids])
    colour_parts, trans_parts, depth_parts, pixel_parts = [], [], [], []
    for t, (piece, z) in enumerate(zip(pieces, depth_pairs, strict=True)):
        ty, tx = divmod(t, ntx)
        vs = torch.arange(ty * tile, min((ty + 1) * tile, height_px))
        us = torch.arange(tx * tile, min((tx + 1) * tile, width_px))
        vv, uu = torch.meshgrid(vs, us, indexing="ij")
        pixel_parts.append((vv * width_px + uu).reshape(-1))
        pix = torch.stack([uu, vv], dim=-1).reshape(-1, 2).to(torch.float32)
        args = (pix, piece[:, 0:2], piece[:, 2:5], piece[:, 5], piece[:, 6:9], z)
        consts = (config.alpha_min, config.alpha_max, config.transmittance_min)
        if torch.is_grad_enabled() and piece.requires_grad and piece.shape[0]:
            out = checkpoint(_render_tile, *args, *consts, use_reentrant=False)
        else:
            out = _render_tile(*args, *consts)
        colour_parts.append(out[0])
        trans_parts.append(out[1])
        depth_parts.append(out[2])
    inverse = torch.empty(width_px * height_px, dtype=torch.long)
    inverse[torch.cat(pixel_parts)] = torch.arange(width_px * height_px)
    colour = torch.cat(colour_parts)[inverse].reshape(height_px, width_px, 3)
    trans = torch.cat(trans_parts)[inverse].reshape(height_px, width_px)
    image = colour + trans[..., None] * background
    alpha = 1 - trans
    with torch.no_grad():
        acc = torch.cat(depth_parts)[inverse].reshape(height_px, width_px)
        a = alpha.detach()
        depth_img = torch.where(
            a >= _ALPHA_DEPTH_MIN, acc / a.clamp(min=1e-12), torch.zeros_like(a)
        )
    logger.debug("reference rasterized %d pairs over %d tiles", pair_ids.numel(), ntx * nty)
    return RenderOutput(image=image, alpha=alpha, depth_m=depth_img, radii_px=radii)
