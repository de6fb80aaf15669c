"""The depth term: the input views' stereo depth as a second target, so that
Gaussians stay on the surfaces the cameras measured and do not drift along their rays where the
image alone cannot tell depth (seen from the wall cameras they look right; from a person's eye,
far off those rays, they are misplaced).

Per step on a view with a target ``t`` (H, W) (the stereo depth of that view's own camera pair,
drawn into it by ``depth.reproject.depth_targets``; NaN where stereo had no confident answer)::

    L_depth = mean over target pixels of |D - alpha * t| / t

``D = sum_i w_i z_i`` is each Gaussian's camera depth composited exactly as colour is (the
rasterizer run once more with colour = depth, on a black background, so it is differentiable
through the same kernels and their slow twin), ``alpha`` the rendered coverage. Where the view
is covered (alpha = 1) this is the relative depth error; where it is not, the term also asks for
coverage, since stereo saw a surface there. Relative, so that near and far surfaces weigh alike
and the weight does not depend on the room's size. The trainer adds ``depth_weight`` x this.
"""

from __future__ import annotations

import torch

from reconstructor.raster import RasterConfig, rasterize
from reconstructor.splats.gaussians import Gaussians


def rendered_depth(
    g: Gaussians,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width_px: int,
    height_px: int,
    raster: RasterConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(D, alpha), each (H, W): the composited camera depth (metres times coverage) and the
    coverage, both differentiable in the Gaussians' parameters."""
    z = g.means_m @ viewmat[2, :3] + viewmat[2, 3]  # (N,) camera-space depth
    colours = z[:, None].expand(-1, 3).contiguous()
    black = torch.zeros(3, device=z.device, dtype=z.dtype)
    out = rasterize(
        g.means_m, g.quats_wxyz, g.log_scales, g.opacity_logits, colours,
        viewmat, K, width_px, height_px, black, raster,
    )  # fmt: skip
    return out.image[..., 0], out.alpha


def depth_loss(
    d: torch.Tensor, alpha: torch.Tensor, target_m: torch.Tensor, min_alpha: float = 0.0
) -> torch.Tensor:
    """``mean |D - alpha t| / t`` over the finite, positive pixels of ``target_m``; 0 (with a
    gradient of zeros) where it has none. With ``min_alpha`` > 0, geometry alone: ``mean |D /
    alpha - t| / t`` over the pixels the render covers at least that much (no pull on
    coverage)."""
    valid = torch.isfinite(target_m) & (target_m > 0)
    if min_alpha > 0:
        valid &= alpha.detach() >= min_alpha
    if not bool(valid.any()):
        return d.sum() * 0.0
    t = target_m[valid]
    if min_alpha > 0:
        return ((d[valid] / alpha[valid] - t).abs() / t).mean()
    return ((d[valid] - alpha[valid] * t).abs() / t).mean()
