"""The fused training loss against its twin: metrics.l1 and metrics.ssim under autograd.

The trainer relies on the fused loss giving the paper's loss value and the gradient of exactly
that value; these tests hold it to the twin on images of odd sizes, with a border mask, a
fractional mask and the random-background fill, and to finite differences.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from reconstructor.splats.image_loss import image_loss

LOSS_RTOL = 1e-5  # float32 sums over ~10^4-10^5 pixels, float64 accumulators
GRAD_REL_NORM = 1e-4  # ||fused - twin|| / ||twin||
GRAD_ATOL_FRACTION = 1e-4  # max |fused - twin| as a fraction of max |twin|


def _case(h: int, w: int, seed: int, fractional: bool = False):
    gen = torch.Generator().manual_seed(seed)
    # a smooth target with edges, and a render that is a noisy, shifted version of it
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    target = torch.stack([xx, yy, (xx * 7).floor() % 2 * 0.8 + 0.1], dim=2).float()
    target = (target + 0.05 * torch.rand(h, w, 3, generator=gen)).clamp(0, 1)
    rendered = (target.roll(2, dims=1) + 0.1 * torch.randn(h, w, 3, generator=gen)).clamp(0, 1)
    mask = torch.ones(h, w)
    mask[:3] = 0  # an undistortion border
    mask[:, -4:] = 0
    if fractional:
        mask[h // 3 : h // 2, w // 4 : w // 2] = 0.4
    fill = torch.rand(3, generator=gen)
    return rendered, target, mask, fill


def _loss_and_grad(rendered, target, mask, fill, weight, backend):
    x = rendered.clone().requires_grad_(True)
    loss, l1_v, ssim_v = image_loss(x, target, mask, weight, fill, backend=backend)
    loss.backward()
    assert x.grad is not None
    return float(loss.detach()), float(l1_v), float(ssim_v), x.grad


@pytest.mark.parametrize(
    ("h", "w", "fractional", "use_fill", "weight"),
    [
        (61, 97, False, True, 0.2),
        (120, 80, True, True, 0.2),
        (33, 47, False, False, 0.7),
        (200, 320, True, True, 0.0),
        (45, 64, False, True, 1.0),
        (7, 5, False, True, 0.2),  # smaller than the 11x11 window
        (333, 21, True, True, 0.2),  # tall: many strips of rows, each with its borders
    ],
)
def test_fused_loss_matches_twin_values_and_gradients(h, w, fractional, use_fill, weight):
    rendered, target, mask, fill = _case(h, w, seed=h + w, fractional=fractional)
    fill_arg = fill if use_fill else None
    twin = _loss_and_grad(rendered, target, mask, fill_arg, weight, "torch")
    fused = _loss_and_grad(rendered, target, mask, fill_arg, weight, "numba")
    for name, a, b in zip(("loss", "l1", "ssim"), twin[:3], fused[:3], strict=True):
        assert b == pytest.approx(a, rel=LOSS_RTOL, abs=1e-7), name
    g_twin, g_fused = twin[3], fused[3]
    assert torch.isfinite(g_fused).all()
    rel = float((g_fused - g_twin).norm() / g_twin.norm())
    assert rel < GRAD_REL_NORM
    assert float((g_fused - g_twin).abs().max()) <= GRAD_ATOL_FRACTION * float(g_twin.abs().max())


def test_fused_gradient_matches_finite_differences():
    """Central differences of the loss computed in float64 (where a float32 loss would drown
    the difference in rounding), against the fused gradient."""
    rendered, target, mask, fill = _case(40, 56, seed=3, fractional=True)
    _, _, _, grad = _loss_and_grad(rendered, target, mask, fill, 0.2, "numba")
    gen = torch.Generator().manual_seed(11)
    eps = 1e-5  # float64: small enough that no pixel's |x - y| changes sign
    for _ in range(4):
        # directions that move many pixels at once, away from the |x - y| kinks
        direction = torch.randn(rendered.shape, generator=gen)
        direction /= direction.norm()
        x64, t64, m64, f64 = (t.double() for t in (rendered, target, mask, fill))
        d64 = direction.double()
        plus, _, _ = image_loss(x64 + eps * d64, t64, m64, 0.2, f64)
        minus, _, _ = image_loss(x64 - eps * d64, t64, m64, 0.2, f64)
        numeric = (float(plus) - float(minus)) / (2 * eps)
        analytic = float((grad.double() * direction.double()).sum())
        assert analytic == pytest.approx(numeric, rel=1e-3, abs=1e-8)


def test_loss_and_gradient_do_not_depend_on_the_number_of_threads():
    """A reconstruction must not change with the machine's core count: the kernels split the
    rows into strips by thread count, and every row must come out bit for bit the same."""
    rendered, target, mask, fill = _case(300, 90, seed=4, fractional=True)  # 4 vs 8 strips
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _loss_and_grad(rendered, target, mask, fill, 0.2, "numba")
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = _loss_and_grad(rendered, target, mask, fill, 0.2, "numba")
    finally:
        numba.set_num_threads(before)
    assert one[:3] == many[:3]
    assert torch.equal(one[3], many[3])


def test_backward_scales_with_the_weight_given_to_the_loss():
    rendered, target, mask, fill = _case(30, 40, seed=5)
    _, _, _, g1 = _loss_and_grad(rendered, target, mask, fill, 0.2, "numba")
    x = rendered.clone().requires_grad_(True)
    loss, _, _ = image_loss(x, target, mask, 0.2, fill)
    (2.5 * loss).backward()
    assert x.grad is not None
    assert torch.allclose(x.grad, 2.5 * g1, rtol=1e-6, atol=0)


def test_no_grad_gives_the_same_values():
    rendered, target, mask, fill = _case(50, 70, seed=7)
    with_grad = _loss_and_grad(rendered, target, mask, fill, 0.2, "numba")
    with torch.no_grad():
        loss, l1_v, ssim_v = image_loss(rendered, target, mask, 0.2, fill)
    assert (float(loss), float(l1_v), float(ssim_v)) == pytest.approx(with_grad[:3], rel=1e-6)


def test_identical_images_give_zero_loss_and_an_empty_mask_no_gradient():
    _, target, mask, _ = _case(24, 32, seed=9)
    loss, l1_v, ssim_v = image_loss(target.clone(), target, mask, 0.2)
    assert float(l1_v) == 0.0
    assert float(ssim_v) == pytest.approx(1.0, abs=1e-5)
    assert float(loss) == pytest.approx(0.0, abs=1e-5)
    x = target.clone().requires_grad_(True)
    loss, _, _ = image_loss(x, target.flip(0), torch.zeros(24, 32), 0.2)
    loss.backward()
    twin, _, _ = image_loss(target, target.flip(0), torch.zeros(24, 32), 0.2, backend="torch")
    assert np.isfinite(float(loss.detach()))
    assert float(loss.detach()) == pytest.approx(float(twin))  # no pixel counts: SSIM term 0
    assert x.grad is not None and float(x.grad.abs().max()) == 0.0


def test_unknown_backend_is_named():
    rendered, target, mask, _ = _case(8, 8, seed=1)
    with pytest.raises(ValueError, match="backend"):
        image_loss(rendered, target, mask, 0.2, backend="cuda")
