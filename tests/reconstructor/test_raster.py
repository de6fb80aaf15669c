"""The CPU rasterizer: numba kernels against the PyTorch twin, finite differences, analytic
single-Gaussian renders, culling, the empty scene, bad input, a small fit, and gsplat's
projection.

Tolerances. Everything is float32. Values: the two paths add the same terms in different
orders (vector lanes vs. matmuls, float32 vs. double cumprod), which moves an image by ~1e-6;
1e-4 leaves room and still catches any wrong term (those move pixels by >= alpha_min = 4e-3).
Gradients: the fast backward recovers transmittance by division and sums per tile in float32,
so it differs from autograd by ~1e-5 of the largest gradient of that input; we allow 1e-3 of it.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch

from reconstructor.raster import RasterConfig, RenderOutput, rasterize

TWIN = RasterConfig(backend="torch")
PARAMS = ("means_m", "quats_wxyz", "log_scales", "opacity_logits", "colors", "background")


def make_scene(
    n: int,
    seed: int,
    width: int = 64,
    height: int = 48,
    *,
    focal: float = 60.0,
    opacity_logit: tuple[float, float] = (-2.0, 3.0),
    scale_m: tuple[float, float] = (0.01, 0.09),
    spread: float = 1.0,
    needles: int = 0,
) -> dict:
    """n random Gaussians 1-3 m in front of an identity camera (a few outside the view); the
    first ``needles`` are 0.5 mm x 0.8 m, and the next ten sit just past the near plane."""
    g = torch.Generator().manual_seed(seed)

    def u(*shape: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(*shape, generator=g)

    z = u(n, lo=1.0, hi=3.0)
    xy = (u(n, 2) - 0.5) * torch.tensor([width / focal, height / focal]) * 1.2 * spread * z[:, None]
    log_scales = torch.log(u(n, 3, lo=scale_m[0], hi=scale_m[1]))
    if needles:
        log_scales[:needles, 0], log_scales[:needles, 1] = math.log(5e-4), math.log(0.8)
        z[needles : needles + 10] = 0.06
    return {
        "means_m": torch.cat([xy, z[:, None]], dim=1),
        "quats_wxyz": torch.randn(n, 4, generator=g),
        "log_scales": log_scales,
        "opacity_logits": u(n, lo=opacity_logit[0], hi=opacity_logit[1]),
        "colors": u(n, 3, lo=-0.1, hi=1.2),
        "viewmat": torch.eye(4),
        "K": torch.tensor(
            [[focal, 0.0, (width - 1) / 2], [0.0, focal * 1.05, (height - 1) / 2], [0, 0, 1]]
        ),
        "width_px": width,
        "height_px": height,
        "background": torch.tensor([0.2, 0.5, 0.9]),
    }


def render(scene: dict, config: RasterConfig = RasterConfig(), grad: bool = False):  # noqa: B008
    """Render; with grad, also return the gradients of a fixed random loss on image and alpha."""
    inputs = {k: (v.clone().requires_grad_(grad) if k in PARAMS else v) for k, v in scene.items()}
    out = rasterize(**inputs, config=config)
    if not grad:
        return out, None
    g = torch.Generator().manual_seed(99)
    w_img = torch.randn(out.image.shape, generator=g)
    w_alpha = torch.randn(out.alpha.shape, generator=g)
    ((out.image * w_img).sum() + (out.alpha * w_alpha).sum()).backward()
    return out, {k: inputs[k].grad for k in PARAMS}


def assert_grads_close(fast: dict, twin: dict, rel: float = 1e-3) -> None:
    for k in PARAMS:
        scale = float(twin[k].abs().max())
        err = float((fast[k] - twin[k]).abs().max())
        assert err <= rel * scale + 1e-7, f"{k}: max error {err:.3g} vs scale {scale:.3g}"


SCENES: dict[str, dict[str, Any]] = {
    "random": dict(n=300, seed=0),
    # many overlapping, nearly opaque Gaussians: pixels terminate early, alpha hits the clamp
    "dense": dict(n=400, seed=1, opacity_logit=(2.0, 8.0), scale_m=(0.03, 0.12), spread=0.4),
    # size not a multiple of the tile: partial tiles on the right and bottom
    "ragged": dict(n=250, seed=2, width=70, height=45),
    # needles, Gaussians at the near plane and large ones, opacity up to sigmoid(9)
    "extreme": dict(
        n=200, seed=21, scale_m=(0.002, 0.5), opacity_logit=(-3.0, 9.0), spread=1.5, needles=50
    ),
    # a trained model's faint Gaussians: many below alpha_min (binned in no tile), the rest
    # listed only in the tiles their alpha_min region reaches, not their whole 3-sigma square
    "faint": dict(n=300, seed=4, opacity_logit=(-8.0, -1.0), scale_m=(0.03, 0.3)),
}


@pytest.mark.parametrize(
    ("name", "tile"),
    [(name, tile) for name in SCENES for tile in (16, 8)] + [("ragged", 12), ("ragged", 5)],
)
def test_fast_matches_twin(name: str, tile: int) -> None:
    """Tiles of 12 and 5 leave some of the kernels' 8-pixel lanes outside every tile."""
    scene = make_scene(**SCENES[name])
    config = RasterConfig(tile_px=tile)
    fast, g_fast = render(scene, config, grad=True)
    twin, g_twin = render(scene, replace(config, backend="torch"), grad=True)
    assert torch.equal(fast.radii_px, twin.radii_px)
    assert int((fast.radii_px > 0).sum()) > 0.5 * len(fast.radii_px)
    torch.testing.assert_close(fast.image, twin.image, atol=1e-4, rtol=0)
    torch.testing.assert_close(fast.alpha, twin.alpha, atol=1e-4, rtol=0)
    torch.testing.assert_close(fast.depth_m, twin.depth_m, atol=1e-4, rtol=1e-4)
    assert_grads_close(g_fast, g_twin)


def test_dense_scene_exercises_termination_and_clamp() -> None:
    """The dense scene above is worth its name: without early termination or without the alpha
    clamp its image changes (so both rules were compared against the twin)."""
    scene = make_scene(**SCENES["dense"])
    base, _ = render(scene)
    no_stop, _ = render(scene, RasterConfig(transmittance_min=0.0))
    no_clamp, _ = render(scene, RasterConfig(alpha_max=0.9999))
    t_final = 1 - base.alpha
    # termination keeps T >= 1e-4, and many pixels sit right at that floor
    assert float(t_final.min()) >= 1e-4 * (1 - 1e-5)
    assert int((t_final < 1e-3).sum()) > 100
    assert float((no_stop.image - base.image).abs().max()) > 1e-3
    assert float((no_clamp.image - base.image).abs().max()) > 1e-3


def test_alpha_only_loss_matches_twin() -> None:
    """A loss on alpha alone (image unused: its gradient is None inside the backward)."""
    scene = make_scene(n=200, seed=3)
    grads = []
    for config in (RasterConfig(), TWIN):
        inputs = {
            k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()
        }
        out = rasterize(**inputs, config=config)
        (out.alpha**2).sum().backward()
        grads.append({k: inputs[k].grad for k in PARAMS if k not in ("colors", "background")})
    for k, g in grads[1].items():
        assert float((grads[0][k] - g).abs().max()) <= 1e-3 * float(g.abs().max()) + 1e-7, k


def _fd_loss(scene: dict, w_img: torch.Tensor, w_alpha: torch.Tensor) -> float:
    out = rasterize(**scene)
    return float((out.image.double() * w_img).sum() + (out.alpha.double() * w_alpha).sum())


def test_backward_matches_central_differences() -> None:
    """Three wide, half-transparent Gaussians covering a small image: every pixel sees every
    Gaussian well above alpha_min, so the loss is smooth and central differences are valid."""
    g = torch.Generator().manual_seed(7)
    scene = make_scene(n=3, seed=7, width=24, height=20, focal=40.0, scale_m=(0.5, 0.8),
                       opacity_logit=(-1.0, 0.5), spread=0.3)  # fmt: skip
    w_img = torch.randn(20, 24, 3, generator=g, dtype=torch.float64)
    w_alpha = torch.randn(20, 24, generator=g, dtype=torch.float64)
    inputs = {k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()}
    out = rasterize(**inputs)
    ((out.image.double() * w_img).sum() + (out.alpha.double() * w_alpha).sum()).backward()
    steps = {"means_m": 2e-3, "quats_wxyz": 2e-3, "log_scales": 2e-3, "opacity_logits": 2e-3,
             "colors": 2e-3, "background": 2e-3}  # fmt: skip
    for k, h in steps.items():
        analytic = inputs[k].grad.double()
        numeric = torch.zeros_like(analytic)
        flat = scene[k].reshape(-1)
        for i in range(flat.numel()):
            plus, minus = dict(scene), dict(scene)
            for sign, s in ((1, plus), (-1, minus)):
                v = flat.clone()
                v[i] += sign * h
                s[k] = v.reshape(scene[k].shape)
            up, down = _fd_loss(plus, w_img, w_alpha), _fd_loss(minus, w_img, w_alpha)
            numeric.view(-1)[i] = (up - down) / (2 * h)
        scale = float(analytic.abs().max())
        err = float((numeric - analytic).abs().max())
        assert err <= 1e-2 * scale + 1e-3, f"{k}: analytic {analytic} vs numeric {numeric}"


def test_single_gaussian_lands_where_the_pinhole_says() -> None:
    """An isotropic Gaussian 2 m ahead, 0.1 m right: its peak is at the projected pixel with
    alpha = opacity, and its neighbours follow the EWA footprint: with J = [[f/z, 0, -f x/z²],
    [0, f/z, 0]], Σ2D = σ² J Jᵀ + eps2d I is diagonal, var_x = σ²(f²/z² + f²x²/z⁴) + eps2d,
    var_y = σ² f²/z² + eps2d."""
    f, cx, cy, z, sigma, x_off = 100.0, 20.0, 15.0, 2.0, 0.05, 0.1
    opacity = 0.7
    scene = {
        "means_m": torch.tensor([[x_off, 0.0, z]]),
        "quats_wxyz": torch.tensor([[0.3, -0.2, 0.5, 0.1]]),  # any rotation: it is isotropic
        "log_scales": torch.full((1, 3), math.log(sigma)),
        "opacity_logits": torch.tensor([math.log(opacity / (1 - opacity))]),
        "colors": torch.tensor([[1.0, 0.5, 0.0]]),
        "viewmat": torch.eye(4),
        "K": torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]),
        "width_px": 48,
        "height_px": 32,
        "background": torch.tensor([0.0, 0.0, 1.0]),
    }
    for config in (RasterConfig(), TWIN):
        out, _ = render(scene, config)
        u_peak, v_peak = round(cx + f * x_off / z), round(cy)  # 25, 15: exactly a pixel centre
        v, u = np.unravel_index(int(out.alpha.argmax()), out.alpha.shape)
        assert (u, v) == (u_peak, v_peak)
        var_x = sigma**2 * (f**2 / z**2 + f**2 * x_off**2 / z**4) + config.eps2d_px2
        var_y = sigma**2 * f**2 / z**2 + config.eps2d_px2
        near = opacity * math.exp(-0.5 / var_x)
        diag = opacity * math.exp(-0.5 * (1 / var_x + 4 / var_y))
        assert float(out.alpha[v, u]) == pytest.approx(opacity, abs=1e-6)
        assert float(out.alpha[v, u + 1]) == pytest.approx(near, abs=1e-6)
        assert float(out.alpha[v + 2, u - 1]) == pytest.approx(diag, abs=1e-6)
        colour, bg = torch.tensor([1.0, 0.5, 0.0]), torch.tensor([0.0, 0.0, 1.0])
        expected = opacity * colour + (1 - opacity) * bg
        torch.testing.assert_close(out.image[v, u], expected, atol=1e-6, rtol=0)
        assert float(out.depth_m[v, u]) == pytest.approx(z, rel=1e-5)
        assert int(out.radii_px[0]) == math.ceil(3 * math.sqrt(max(var_x, var_y)))
        assert float(out.alpha[0, 0]) == 0.0 and float(out.depth_m[0, 0]) == 0.0


def test_culled_gaussians_have_zero_radius_and_gradient() -> None:
    scene = make_scene(n=40, seed=4)
    culled = torch.tensor(
        [
            [0.0, 0.0, -2.0],  # behind the camera
            [0.0, 0.0, 0.01],  # in front of the near plane (0.05 m)
            [0.0, 0.0, 500.0],  # beyond the far plane (100 m)
            [50.0, 0.0, 2.0],  # far right of the image
            [0.0, -40.0, 2.0],  # far above it
        ]
    )
    k = len(culled)
    more = make_scene(n=k, seed=5)
    full = dict(scene)
    for key in PARAMS[:5]:
        full[key] = torch.cat([scene[key], culled if key == "means_m" else more[key]])
    for config in (RasterConfig(), TWIN):
        out, grads = render(full, config, grad=True)
        assert out.radii_px.dtype == torch.int32
        assert torch.all(out.radii_px[-k:] == 0)
        for key in PARAMS[:5]:
            assert torch.all(grads[key][-k:] == 0), key
            assert float(grads[key][:-k].abs().max()) > 0, key
        alone, _ = render(scene, config)
        torch.testing.assert_close(out.image, alone.image, atol=1e-6, rtol=0)


def test_empty_scene_is_the_background() -> None:
    scene = make_scene(n=0, seed=0, width=20, height=10)
    for config in (RasterConfig(), TWIN):
        bg = scene["background"].clone().requires_grad_(True)
        out = rasterize(**{**scene, "background": bg}, config=config)
        assert isinstance(out, RenderOutput)
        torch.testing.assert_close(out.image, scene["background"].expand(10, 20, 3))
        assert float(out.alpha.detach().abs().max()) == 0.0
        assert float(out.depth_m.abs().max()) == 0.0
        assert out.radii_px.shape == (0,)
        out.image.sum().backward()
        torch.testing.assert_close(bg.grad, torch.full((3,), 200.0))


def test_gradients_are_deterministic() -> None:
    scene = make_scene(n=300, seed=6)
    _, a = render(scene, grad=True)
    _, b = render(scene, grad=True)
    for k in PARAMS:
        assert torch.equal(a[k], b[k]), k


def test_fitting_a_target_reduces_the_loss_tenfold() -> None:
    """Recover colours and positions of 100 Gaussians from an image they rendered."""
    truth = make_scene(n=100, seed=8, scale_m=(0.05, 0.12), opacity_logit=(0.0, 3.0))
    with torch.no_grad():
        target = rasterize(**truth).image
    g = torch.Generator().manual_seed(9)
    colors = torch.rand(100, 3, generator=g).requires_grad_(True)
    means = (truth["means_m"] + 0.03 * torch.randn(100, 3, generator=g)).requires_grad_(True)
    opt = torch.optim.Adam([{"params": [colors], "lr": 0.05}, {"params": [means], "lr": 2e-3}])
    losses = []
    for _ in range(150):
        opt.zero_grad()
        out = rasterize(**{**truth, "colors": colors, "means_m": means})
        loss = ((out.image - target) ** 2).mean()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(means_m=torch.zeros(5, 2)), "means_m"),
        (dict(quats_wxyz=torch.zeros(4, 4) + 1), "quats_wxyz"),
        (dict(log_scales=torch.zeros(5, 3, dtype=torch.float64)), "log_scales"),
        (dict(opacity_logits=torch.tensor([0.0, 1, float("nan"), 0, 0])), "opacity_logits"),
        (dict(colors=torch.full((5, 3), float("inf"))), "colors"),
        (dict(background=torch.zeros(4)), "background"),
        (dict(viewmat=torch.eye(3)), "viewmat"),
        (dict(K=torch.zeros(3, 3)), "K"),
        (dict(width_px=0), "width_px"),
        (dict(height_px=2.5), "height_px"),
        (dict(quats_wxyz=torch.zeros(5, 4)), "quats_wxyz"),
    ],
)
def test_bad_input_names_the_argument(change: dict, message: str) -> None:
    scene = {**make_scene(n=5, seed=0), **change}
    with pytest.raises(ValueError, match=message):
        rasterize(**scene)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(tile_px=0),
        dict(tile_px=64),
        dict(near_m=0.0),
        dict(far_m=0.01),
        dict(eps2d_px2=-1.0),
        dict(alpha_min=0.0),
        dict(alpha_max=1.0),
        dict(transmittance_min=1.0),
        dict(sigma_extent=float("nan")),
        dict(backend="cuda"),
    ],
)
def test_bad_config_names_the_field(kwargs: dict) -> None:
    (field,) = kwargs
    with pytest.raises(ValueError, match=field):
        RasterConfig(**kwargs)


def test_projection_agrees_with_gsplat() -> None:
    """Our projection (numba and twin) against gsplat's pure-PyTorch reference, on Gaussians
    whose centres project inside the image (there both clamp nothing; gsplat's frustum limits
    put the pixel edge at W where ours put it at W - 0.5, and its radius is per axis)."""
    gs = pytest.importorskip("gsplat.cuda._torch_impl")
    from reconstructor.raster import projection
    from reconstructor.raster.reference import project_reference

    scene = make_scene(n=500, seed=10, spread=0.8)
    scene["viewmat"] = torch.tensor(
        [[0.96, -0.28, 0.0, 0.1], [0.28, 0.96, 0.0, -0.2], [0.0, 0.0, 1.0, 0.3], [0, 0, 0, 1]]
    )
    w, h, cfg = scene["width_px"], scene["height_px"], RasterConfig()
    quats = scene["quats_wxyz"]
    covars, _ = gs._quat_scale_to_covar_preci(quats, torch.exp(scene["log_scales"]), True, False)
    radii_gs, means2d_gs, depth_gs, conics_gs, _ = gs._fully_fused_projection(
        scene["means_m"], covars, scene["viewmat"][None], scene["K"][None], w, h,
        eps2d=cfg.eps2d_px2, near_plane=cfg.near_m, far_plane=cfg.far_m,
    )  # fmt: skip
    fast = projection.project(
        *(scene[k].numpy() for k in PARAMS[:5]), scene["viewmat"].double().numpy(),
        scene["K"].double().numpy(), w, h, cfg.tile_px, cfg.near_m, cfg.far_m, cfg.eps2d_px2,
        cfg.sigma_extent, cfg.alpha_min,
    )  # fmt: skip
    twin = project_reference(
        scene["means_m"], quats, scene["log_scales"], scene["viewmat"].double(),
        scene["K"].double(), w, h, cfg,
    )  # fmt: skip
    m2d = means2d_gs[0]
    inside = (m2d[:, 0] > 0) & (m2d[:, 0] < w - 1) & (m2d[:, 1] > 0) & (m2d[:, 1] < h - 1)
    assert int(inside.sum()) > 100
    visible_gs = radii_gs[0].amax(-1) > 0
    assert torch.equal(inside & visible_gs, inside & (torch.from_numpy(fast.radii) > 0))
    p = torch.from_numpy(fast.proj)
    mean_cols = [projection.MX, projection.MY]
    conic_cols = [projection.CA, projection.CB, projection.CC]
    torch.testing.assert_close(p[inside][:, mean_cols], m2d[inside], atol=1e-3, rtol=1e-5)
    depth = p[inside, projection.DEPTH]
    torch.testing.assert_close(depth, depth_gs[0][inside], atol=1e-5, rtol=1e-5)
    conics = p[inside][:, conic_cols]
    torch.testing.assert_close(conics, conics_gs[0][inside], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(twin[0][inside], m2d[inside], atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(twin[1][inside], conics_gs[0][inside], atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize(("name", "tile"), [(name, 16) for name in SCENES] + [("ragged", 5)])
def test_render_only_path_matches_training_path_bit_for_bit(name: str, tile: int) -> None:
    """Without a gradient to follow, rasterize takes kernels.raster_render (no backward
    bookkeeping); its outputs must be the training forward's exactly, whichever way the
    gradient is ruled out."""
    scene = make_scene(**SCENES[name])
    config = RasterConfig(tile_px=tile)
    train, _ = render(scene, config, grad=True)
    with torch.no_grad():
        no_grad = rasterize(
            **{k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()},
            config=config,
        )
    plain, _ = render(scene, config, grad=False)  # grad mode on, no input requires grad
    for out in (no_grad, plain):
        assert not out.image.requires_grad and not out.alpha.requires_grad
        for field in ("image", "alpha", "depth_m", "radii_px"):
            a, b = getattr(train, field).detach(), getattr(out, field)
            assert a.dtype == b.dtype and torch.equal(a, b), field


def _binning_inputs(n: int, seed: int, ties: bool) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.05, 100.0, n).astype(np.float32)
    if ties:
        depth = np.round(depth, 0).astype(np.float32)  # many equal keys
    radii = np.where(rng.random(n) < 0.7, rng.integers(1, 40, n), 0).astype(np.int32)
    x0, y0 = rng.integers(0, 8, n), rng.integers(0, 5, n)
    x1, y1 = np.minimum(x0 + rng.integers(0, 3, n), 7), np.minimum(y0 + rng.integers(0, 3, n), 4)
    rect = np.stack([x0, x1, y0, y1], axis=1).astype(np.int32)
    return depth.view(np.uint32), radii, rect


@pytest.mark.parametrize(("n", "ties"), [(0, False), (1, False), (3000, False), (3000, True)])
def test_binning_matches_a_stable_argsort(n: int, ties: bool) -> None:
    """bin_gaussians (radix sort on the key range, chunked fill) against the obvious version:
    a stable argsort of the depths and a loop over the tiles."""
    from reconstructor.raster import kernels

    depth_bits, radii, rect = _binning_inputs(n, seed=n + ties, ties=ties)
    ntx, n_tiles = 8, 40
    for chunks in (1, 3):
        pairs, offsets, slots, goffsets = kernels.bin_gaussians(
            depth_bits, radii, rect, ntx, n_tiles, chunks
        )
        order = [int(i) for i in np.argsort(depth_bits, kind="stable") if radii[i] > 0]
        covered = np.where(
            radii > 0, (rect[:, 1] - rect[:, 0] + 1) * (rect[:, 3] - rect[:, 2] + 1), 0
        )
        assert np.array_equal(goffsets, np.concatenate([[0], np.cumsum(covered)]))
        numbers: dict[tuple[int, int], int] = {}
        for g in range(n):  # pair (tile, g) is number goffsets[g] + its rank in g's rectangle
            if radii[g] > 0:
                tiles = [ty * ntx + tx for ty in range(rect[g, 2], rect[g, 3] + 1)
                         for tx in range(rect[g, 0], rect[g, 1] + 1)]  # fmt: skip
                numbers.update({(t, g): int(goffsets[g]) + r for r, t in enumerate(tiles)})
        for t in range(n_tiles):
            want = [g for g in order if (t, g) in numbers]
            got = pairs[offsets[t] : offsets[t + 1]]
            assert got.tolist() == want, t
            assert slots[offsets[t] : offsets[t + 1]].tolist() == [numbers[t, g] for g in want]
        render_only = kernels.bin_gaussians(depth_bits, radii, rect, ntx, n_tiles, chunks, False)
        assert np.array_equal(render_only[0], pairs) and np.array_equal(render_only[1], offsets)
        assert render_only[2].shape == (0,)


@pytest.mark.parametrize(
    ("key", "bad"),
    [("means_m", float("nan")), ("colors", float("inf")), ("log_scales", float("-inf"))],
)
def test_bad_values_in_large_inputs_name_the_argument(key: str, bad: float) -> None:
    """Large inputs take validate_inputs' parallel checks; they must catch what the small do."""
    scene = make_scene(n=40_000, seed=11)
    scene[key] = scene[key].clone()
    scene[key][12_345, 1] = bad
    with pytest.raises(ValueError, match=f"{key} has non-finite"):
        rasterize(**scene)
    scene = make_scene(n=40_000, seed=11)
    scene["quats_wxyz"][39_999] = 0.0
    with pytest.raises(ValueError, match="quats_wxyz has a zero quaternion"):
        rasterize(**scene)


def test_tile_lists_hold_a_gaussian_only_where_its_alpha_can_reach() -> None:
    """Binning by the alpha_min region instead of the 3-sigma square: a faint Gaussian is
    listed in fewer tiles, one below alpha_min in none, and both keep their radius."""
    from reconstructor.raster import projection

    tile, width, height = 4, 128, 96
    scene = make_scene(2, seed=0, width=width, height=height)
    means = np.array([[0.0, 0.0, 2.0], [0.1, 0.05, 2.0]], np.float32)
    log_scales = np.log(np.full((2, 3), 0.3, np.float32))  # sigma = 9 px: 3-sigma = 27 px
    logits = np.array([math.log(0.02 / 0.98), math.log(0.002 / 0.998)], np.float32)
    quats = np.array([[1, 0, 0, 0]] * 2, np.float32)
    p = projection.project(
        means, quats, log_scales, logits, np.ones((2, 3), np.float32),
        scene["viewmat"].double().numpy(), scene["K"].double().numpy(), width, height, tile,
        0.05, 100.0, 0.3, 3.0, 1 / 255,
    )  # fmt: skip
    assert (p.radii > 0).all()
    x0, x1, y0, y1 = p.rect[0]
    r = int(p.radii[0])
    mx, my = p.proj[0, projection.MX], p.proj[0, projection.MY]
    square_tiles = (math.floor(mx + r) // tile - math.ceil(mx - r) // tile + 1) * (
        math.floor(my + r) // tile - math.ceil(my - r) // tile + 1
    )
    faint_tiles = (x1 - x0 + 1) * (y1 - y0 + 1)
    assert 0 < faint_tiles < 0.6 * square_tiles
    # alpha = 0.02 exp(-d²/2σ²) reaches 1/255 within 2.0 sigma: every tile that holds such a
    # pixel is listed
    reach = 9.0 * math.sqrt(2 * math.log(0.02 * 255)) * 0.99
    assert x0 * tile <= mx - reach and (x1 + 1) * tile > mx + reach
    assert y0 * tile <= my - reach * 1.05 and (y1 + 1) * tile > my + reach * 1.05
    bx0, bx1, by0, by1 = p.rect[1]
    assert bx1 < bx0 and by1 < by0  # below alpha_min: an empty rectangle


def test_lane_block_rows_hold_every_pixel_the_alpha_region_reaches() -> None:
    """The rows a Gaussian visits in one 8-column lane block: every pixel of the block where
    its alpha can reach alpha_min lies in them, and they are no taller than that region's
    extent over the block's columns (checked by brute force on random rotated ellipses)."""
    from reconstructor.raster import kernels

    rng = np.random.default_rng(5)
    narrowed = 0
    for _ in range(400):
        sx, sy = rng.uniform(0.5, 12.0, size=2)
        theta = rng.uniform(0, math.pi)
        rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
        cov = rot @ np.diag([sx * sx, sy * sy]) @ rot.T
        conic = np.linalg.inv(cov).astype(np.float32)
        a, b, c = (float(v) for v in (conic[0, 0], conic[0, 1], conic[1, 1]))
        span = 2.0 * math.log(rng.uniform(0.01, 0.99) * 255)  # q <= span: alpha >= 1/255
        hx = np.float32(math.sqrt(span * 1.001 * cov[0, 0]))  # as the projection widens it
        hy = np.float32(math.sqrt(span * 1.001 * cov[1, 1]))
        mx, my = (np.float32(v) for v in rng.uniform(0, 32, size=2))
        y0, r0, r1 = 0, 0, 31  # a 32-row tile at row 0, all rows allowed
        u_first = int(rng.integers(-8, 40))
        q0, q1 = kernels._strip_rows(
            np.float32(a), np.float32(b), np.float32(c), mx, my, hx, hy, u_first,
            u_first + 7, y0, r0, r1,
        )  # fmt: skip
        cols = np.arange(u_first, u_first + 8, dtype=np.float64)
        rows = np.arange(0, 32, dtype=np.float64)
        dx = cols[None, :] - float(mx)
        dy = rows[:, None] - float(my)
        q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
        reached = np.nonzero((q <= span).any(axis=1))[0]
        if len(reached):
            assert q0 <= reached.min() and reached.max() <= q1, (q0, q1, reached)
        # not taller than the region over the block's continuous columns, plus a row
        fine = np.linspace(u_first, u_first + 7, 281) - float(mx)
        ys = np.linspace(-40, 72, 4481) - float(my)
        qf = a * fine[None, :] ** 2 + 2 * b * fine[None, :] * ys[:, None] + c * ys[:, None] ** 2
        inside = np.nonzero((qf <= span * 1.002).any(axis=1))[0]
        if q0 <= q1:
            assert len(inside), (q0, q1)
            lo, hi = ys[inside].min() + float(my), ys[inside].max() + float(my)
            assert q0 >= math.floor(lo) - 1 and q1 <= math.ceil(hi) + 1, (q0, q1, lo, hi)
            full = (math.ceil(my - hy), math.floor(my + hy))
            narrowed += (q1 - q0) < min(31, full[1]) - max(0, full[0])
    assert narrowed > 50  # the case this exists for: rotated Gaussians over several blocks


def test_elongated_rotated_gaussians_over_many_lane_blocks_match_the_twin() -> None:
    """Long thin Gaussians at all angles, each spanning several lane blocks of 32-pixel tiles
    (where a block visits only the rows the Gaussian reaches there): values and gradients
    match the twin."""
    scene = make_scene(
        80, seed=11, width=96, height=64, scale_m=(0.002, 0.25), opacity_logit=(-4.0, 2.0),
        needles=12,
    )  # fmt: skip
    config = RasterConfig(tile_px=32)
    fast, g_fast = render(scene, config, grad=True)
    twin, g_twin = render(scene, replace(config, backend="torch"), grad=True)
    torch.testing.assert_close(fast.image, twin.image, atol=1e-4, rtol=0)
    torch.testing.assert_close(fast.alpha, twin.alpha, atol=1e-4, rtol=0)
    assert_grads_close(g_fast, g_twin)


def test_the_compositing_exponential_is_as_accurate_as_float32_allows() -> None:
    """Every fragment's alpha is 2^e through ``kernels.exp2_neg``: across the exponents a
    fragment can have (from far below alpha_min up to opacity 1), within 2e-7 of the true
    value, relative (a few float32 ulps), and 2^-126 below the clamp."""
    from reconstructor.raster.kernels import exp2_neg

    t = np.concatenate([np.linspace(-126.0, 0.5, 200_001), [-0.5, 0.0, 0.25, -60.5]])
    t32 = t.astype(np.float32)
    got = np.array([exp2_neg(v) for v in t32], np.float64)
    want = np.exp2(t32.astype(np.float64))
    assert float(np.max(np.abs(got - want) / want)) < 2e-7
    assert exp2_neg(np.float32(0.0)) == 1.0
    assert exp2_neg(np.float32(-300.0)) == np.float32(2.0**-126)
