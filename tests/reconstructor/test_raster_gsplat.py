"""gsplat's CUDA rasterizer behind ``rasterize()`` (``RasterConfig(backend="gsplat")``): its
forward and gradients against our numba kernels on the same Gaussians and cameras (marked
``gpu``: they run where CUDA and gsplat are), and, everywhere else, the CUDA backend's one-line
refusals (CI has no GPU).

The comparison runs the numba kernels with gsplat's compiled clamp (``alpha_max = 0.999``) and
an extent of 3.33 sigma: gsplat's per-axis 3.33-sigma box (tightened by opacity) then leaves
out only fragments whose alpha is below 1/255, which both skip, so both composite the same
fragments in the same order. What is left is float32 rounding (gsplat is built with fast math)
and, rarely, a fragment whose alpha lands on either side of 1/255 in the two: that moves a pixel
by at most alpha_min x the colour range (1.3) ~ 5e-3. Tolerances:

- image and alpha: mean |difference| <= 1e-4, max <= 1e-2 (two such fragments);
- depth where both alphas exceed 0.5: <= 1e-3 relative;
- gradients of a random loss on image and alpha: ||g_gsplat - g_numba|| <= 2e-2 ||g_numba||
  per input (float32 sums in other orders, atomics on the GPU);
- visibility: every Gaussian of opacity >= 0.05 whose centre projects inside the image between
  the planes has a radius > 0 in both.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reconstructor.errors import GpuUnavailableError
from reconstructor.raster import RasterConfig, rasterize
from reconstructor.raster.device import for_device
from reconstructor.raster.gsplat_backend import require_gpu
from tests.helpers import run_egosurg
from tests.reconstructor.test_raster import PARAMS, SCENES, make_scene

NUMBA_AS_GSPLAT = RasterConfig(alpha_max=0.999, sigma_extent=3.33)
GSPLAT = RasterConfig(backend="gsplat")
GRAD_REL = 2e-2

has_cuda = torch.cuda.is_available()
cpu_only = pytest.mark.skipif(has_cuda, reason="checks the refusal where there is no CUDA")


@pytest.fixture(scope="module")
def gsplat_ready() -> None:
    try:
        require_gpu()
    except GpuUnavailableError as e:
        pytest.skip(str(e))


def _render(scene: dict, config: RasterConfig, device: str):
    """Render on ``device`` with gradients of a fixed random loss on image and alpha."""
    inputs = {
        k: (v.to(device).clone().requires_grad_(True) if k in PARAMS else v)
        for k, v in scene.items()
    }
    out = rasterize(**inputs, config=config)
    g = torch.Generator().manual_seed(99)
    w_img = torch.randn(tuple(out.image.shape), generator=g).to(out.image.device)
    w_alpha = torch.randn(tuple(out.alpha.shape), generator=g).to(out.image.device)
    ((out.image * w_img).sum() + (out.alpha * w_alpha).sum()).backward()
    grads = {k: inputs[k].grad.detach().cpu() for k in PARAMS}
    return {
        k: getattr(out, k).detach().cpu() for k in ("image", "alpha", "depth_m", "radii_px")
    }, grads


def compare(scene: dict) -> dict[str, float]:
    """The differences the module docstring bounds, for one scene (also printed by
    bench/bench_gpu.py)."""
    ours, g_ours = _render(scene, NUMBA_AS_GSPLAT, "cpu")
    theirs, g_theirs = _render(scene, GSPLAT, "cuda")
    out: dict[str, float] = {}
    for k in ("image", "alpha"):
        d = (ours[k] - theirs[k]).abs()
        out[f"{k}_mean"], out[f"{k}_max"] = float(d.mean()), float(d.max())
    both = (ours["alpha"] > 0.5) & (theirs["alpha"] > 0.5)
    rel = (ours["depth_m"] - theirs["depth_m"]).abs() / ours["depth_m"].abs().clamp_min(1e-6)
    out["depth_rel_max"] = float(rel[both].max()) if both.any() else 0.0
    for k in PARAMS:
        ref = float(g_ours[k].norm())
        out[f"grad_{k}"] = float((g_theirs[k] - g_ours[k]).norm()) / max(ref, 1e-12)
    means, K = scene["means_m"], scene["K"]
    z = means[:, 2]
    u = K[0, 0] * means[:, 0] / z + K[0, 2]
    v = K[1, 1] * means[:, 1] / z + K[1, 2]
    w, h = scene["width_px"], scene["height_px"]
    must = (
        (torch.sigmoid(scene["opacity_logits"]) >= 0.05) & (z > GSPLAT.near_m)
        & (u > 0) & (u < w - 1) & (v > 0) & (v < h - 1)
    )  # fmt: skip
    seen = (ours["radii_px"] > 0) & (theirs["radii_px"] > 0)
    out["missed_visible"] = float((must & ~seen).sum())
    return out


@pytest.mark.parametrize("name", list(SCENES))
@pytest.mark.usefixtures("gsplat_ready")
@pytest.mark.gpu
@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_gsplat_matches_the_numba_kernels(name: str) -> None:
    """The same Gaussians and camera give the same image, alpha, depth and gradients on the
    GPU as on the CPU, within the tolerances of the module docstring."""
    d = compare(make_scene(**SCENES[name]))
    assert d["image_mean"] <= 1e-4 and d["image_max"] <= 1e-2, d
    assert d["alpha_mean"] <= 1e-4 and d["alpha_max"] <= 1e-2, d
    assert d["depth_rel_max"] <= 1e-3, d
    for k in PARAMS:
        assert d[f"grad_{k}"] <= GRAD_REL, (k, d)
    assert d["missed_visible"] == 0, d


@pytest.mark.usefixtures("gsplat_ready")
@pytest.mark.gpu
@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_a_pixel_centre_lands_where_the_pinhole_says_on_the_gpu() -> None:
    """One small Gaussian on the optical axis of a camera whose principal point is a pixel
    centre: the brightest pixel is that pixel, on both backends (the +0.5 shift of gsplat's
    pixel centres is applied)."""
    for cx, cy in ((20.0, 15.0), (33.0, 7.0), (5.0, 28.0)):
        scene = {
            "means_m": torch.tensor([[0.0, 0.0, 2.0]]),
            "quats_wxyz": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
            "log_scales": torch.full((1, 3), math.log(0.004)),
            "opacity_logits": torch.tensor([4.0]),
            "colors": torch.tensor([[1.0, 1.0, 1.0]]),
            "viewmat": torch.eye(4),
            "K": torch.tensor([[80.0, 0, cx], [0, 80.0, cy], [0, 0, 1]]),
            "width_px": 48,
            "height_px": 32,
            "background": torch.zeros(3),
        }
        for config, dev in ((NUMBA_AS_GSPLAT, "cpu"), (GSPLAT, "cuda")):
            out, _ = _render(scene, config, dev)
            img = out["image"][..., 0].numpy()
            row, col = np.unravel_index(np.argmax(img), img.shape)
            assert (col, row) == (int(cx), int(cy)), dev


@pytest.mark.usefixtures("gsplat_ready")
@pytest.mark.gpu
@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_the_render_command_on_cuda_draws_what_the_cpu_draws(tmp_path) -> None:
    """``egosurg render --device cuda`` through the real command: the same PNG as on the CPU,
    within one grey level where the numba clamp (0.99) and gsplat's (0.999) agree."""
    import cv2

    from reconstructor.splats import ply
    from reconstructor.splats.gaussians import SH_C0, Gaussians

    scene = make_scene(n=400, seed=5, spread=0.6)
    x, y, z = scene["means_m"].unbind(1)  # camera axes -> a world looking along +x, z up
    g = Gaussians(
        means_m=torch.stack([z, -x, -y], dim=1).contiguous(), quats_wxyz=scene["quats_wxyz"],
        log_scales=scene["log_scales"], opacity_logits=scene["opacity_logits"].clamp(max=3.0),
        sh_dc=(scene["colors"].clamp(0, 1) - 0.5) / SH_C0, sh_rest=torch.zeros(400, 0, 3),
    )  # fmt: skip
    model = ply.write_ply(tmp_path / "splats.ply", g)
    images = {}
    for device in ("cpu", "cuda"):
        out = tmp_path / f"{device}.png"
        done = run_egosurg(
            "render", str(model), "--camera", "eye=0,0,0 target=1,0,0", "--size", "320x240",
            "--out", str(out), "--device", device, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        png = cv2.imread(str(out))
        assert png is not None, f"{out} was not written"
        images[device] = png.astype(int)
    assert images["cpu"].std() > 10  # the Gaussians are in view
    diff = np.abs(images["cpu"] - images["cuda"])
    assert diff.max() <= 3 and diff.mean() < 0.05, (diff.max(), diff.mean())


# ---- where there is no CUDA (CI) ----------------------------------------------------------------
def _egosurg_here(capsys, *args: str) -> tuple[int, str]:
    """The real dispatcher (protocol/cli.py) in this process: (exit code, stderr); torch is
    loaded once, not per command."""
    from protocol.cli import main

    capsys.readouterr()
    code = main(list(args))
    return code, capsys.readouterr().err


@cpu_only
def test_device_cuda_without_a_gpu_is_one_clear_line(tmp_path, capsys) -> None:
    """``--device cuda`` on a machine without CUDA says so, and how to install the extra, in
    one line: no traceback from deep inside gsplat."""
    from reconstructor.splats import ply
    from reconstructor.splats.gaussians import init_from_points

    model = tmp_path / "splats.ply"
    ply.write_ply(model, init_from_points(np.random.default_rng(0).random((20, 3)),
                                          np.full((20, 3), 0.5)))  # fmt: skip
    code, err = _egosurg_here(
        capsys, "render", str(model), "--camera", "eye=2,2,2 target=0,0,0", "--out",
        str(tmp_path / "v.png"), "--device", "cuda",
    )  # fmt: skip
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "--device cuda" in lines[0] and "egosurg[gpu]" in lines[0]
    assert not (tmp_path / "v.png").exists()


@cpu_only
def test_evaluate_on_cuda_without_a_gpu_stops_before_reading_anything(tmp_path, capsys) -> None:
    code, err = _egosurg_here(
        capsys, "evaluate", str(tmp_path / "none"), "--out", str(tmp_path / "eval"),
        "--device", "cuda",
    )  # fmt: skip
    assert code == 2 and "Traceback" not in err, err
    assert "--device cuda" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "eval").exists()


@cpu_only
def test_training_on_cuda_without_a_gpu_is_refused_before_any_step() -> None:
    from reconstructor.splats.gaussians import init_from_points
    from reconstructor.splats.train import TrainConfig, Trainer

    g = init_from_points(np.random.default_rng(1).random((10, 3)), np.full((10, 3), 0.5))
    with pytest.raises(GpuUnavailableError, match=r"--device cuda: torch .* (without CUDA|no)"):
        Trainer(g, TrainConfig(), GSPLAT, 1.0)
    assert g.means_m.device.type == "cpu"  # nothing moved


def test_gsplat_refuses_thresholds_its_kernels_do_not_have() -> None:
    """gsplat compiles in alpha_min = 1/255 and transmittance_min = 1e-4: a config asking the
    gsplat backend for others is refused, naming the field, instead of silently ignored."""
    with pytest.raises(ValueError, match=r"RasterConfig.alpha_min=0.01: gsplat compiles in"):
        RasterConfig(backend="gsplat", alpha_min=0.01)
    with pytest.raises(ValueError, match=r"transmittance_min=0.001"):
        RasterConfig(backend="gsplat", transmittance_min=1e-3)
    assert RasterConfig(backend="gsplat").device == "cuda"
    assert RasterConfig().device == "cpu"


def test_a_model_made_on_a_gpu_renders_on_the_cpu_by_default() -> None:
    """A case reconstructed with --device cuda saves backend "gsplat" in its config.toml; the
    commands that read models render on the CPU unless --device cuda is given."""
    made = RasterConfig(backend="gsplat", near_m=0.1)
    on_cpu = for_device(made, "cpu")
    assert on_cpu.backend == "numba" and on_cpu.near_m == 0.1
    assert for_device(RasterConfig(), None) == RasterConfig()
