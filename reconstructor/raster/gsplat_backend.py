"""``rasterize()`` on gsplat's CUDA rasterizer (``RasterConfig(backend="gsplat")``, the ``gpu``
extra): the same function as the numba kernels, our conventions mapped onto gsplat's.

Mapping (ours -> ``gsplat.rasterization``, gsplat 1.4-1.5):

==================  ==========================================  ================================
convention          ours (``function.py``)                      gsplat
==================  ==========================================  ================================
pixel centres       pixel (u, v) at the image point (u, v)      at (u + 0.5, v + 0.5): we pass K
                                                                with cx, cy + 0.5
camera              ``viewmat`` world-to-camera, OpenCV axes    the same (``viewmats``)
rotation            ``quats_wxyz``, any norm                    the same; normalised inside,
                                                                differentiably
scale, opacity      ``log_scales``, ``opacity_logits``          ``exp``, ``sigmoid`` of them (in
                                                                autograd, before the call)
colour              (N, 3) RGB, SH degree 0                     ``colors`` (N, 3),
                                                                ``sh_degree=None``
background          (3,), with its gradient Σ T dL/dC           ``backgrounds`` (1, 3), the same
near / far plane    cull if the centre's z outside [near, far]  ``near_plane``, ``far_plane``
low-pass filter     ``eps2d_px2`` on Σ2D's diagonal             ``eps2d``, ``classic`` mode
alpha threshold     skip α < ``alpha_min`` (1/255)              compiled in: 1/255
stop                T (1 - α) < ``transmittance_min`` (1e-4)    compiled in: T (1 - α) <= 1e-4
alpha clamp         ``alpha_max`` (0.99)                        compiled in: 0.999
screen extent       ``sigma_extent`` (3) σ of the major axis     min(3.33, √(2 ln(255 o))) σ per
                                                                axis: differs only where α < 1/255
tiles               ``tile_px`` (32: a CPU choice)              16 (its kernels' choice)
depth               Σ z α T / alpha, 0 where alpha < 1e-3       ``RGB+ED`` / alpha, then the same
radii               (N,) int32, 0 where culled                  max of its (N, 2) x/y radii
==================  ==========================================  ================================

``alpha_min`` and ``transmittance_min`` decide which fragments draw, so a config whose values
differ from gsplat's compiled ones is refused (``RasterConfig``); ``alpha_max`` is documented,
not enforced: it clamps only fragments above 0.99 and a default config must run on either
backend. ``tests/reconstructor/test_raster_gsplat.py`` (marked ``gpu``) checks forward and
gradients against the numba kernels with ``alpha_max = 0.999``.

Inputs may sit on the CPU: they are copied to the GPU inside autograd and the outputs copied
back, so any caller works; the trainer keeps the model and its views on the GPU instead
(``splats/train.py``), once per run.
"""

from __future__ import annotations

import functools
import importlib
import logging
from typing import Any

import torch

from reconstructor.errors import GpuUnavailableError
from reconstructor.raster.config import RasterConfig, RenderInputs, RenderOutput

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'egosurg[gpu]' (gsplat; it compiles its CUDA code on first use)"
GSPLAT_TILE_PX = 16
_DEPTH_ALPHA_MIN = 1e-3  # as the numba kernels: no depth where almost nothing was drawn


@functools.cache
def gsplat_module() -> Any:
    """The ``gsplat`` package, with its CUDA extension loaded, or a one-line error saying what
    is missing. Checked once per process (gsplat's first import may compile for minutes)."""
    if not torch.cuda.is_available():
        built = torch.version.cuda
        why = (
            f"torch {torch.__version__} is built without CUDA"
            if built is None
            else f"torch {torch.__version__} (CUDA {built}) sees no CUDA device"
        )
        raise GpuUnavailableError(
            f"--device cuda: {why}; run on a machine with an NVIDIA GPU and a CUDA build of "
            f"torch, then {INSTALL_HINT}; or leave out --device cuda to run on the CPU"
        )
    try:
        gsplat = importlib.import_module("gsplat")
    except ImportError as e:
        raise GpuUnavailableError(
            f"--device cuda needs gsplat, which is not installed ({e}): {INSTALL_HINT}"
        ) from e
    try:
        from gsplat.cuda._backend import _C  # the compiled kernels (or JIT-compiled now)
    except Exception as e:  # a failed compile surfaces as many exception types
        raise GpuUnavailableError(
            f"--device cuda: gsplat {getattr(gsplat, '__version__', '?')} could not load its "
            f"CUDA kernels ({type(e).__name__}: {e}); check that nvcc matches torch's CUDA "
            f"{torch.version.cuda}, or install a prebuilt gsplat wheel"
        ) from e
    if _C is None:
        raise GpuUnavailableError(
            f"--device cuda: gsplat {gsplat.__version__} has no CUDA kernels and could not "
            f"compile them (no CUDA toolkit found: set CUDA_HOME to one matching torch's CUDA "
            f"{torch.version.cuda}); or install a prebuilt gsplat wheel"
        )
    log.info("gsplat %s on %s", gsplat.__version__, torch.cuda.get_device_name())
    return gsplat


def require_gpu() -> None:
    """Raise :class:`GpuUnavailableError` (one line) unless the gsplat backend can run here."""
    gsplat_module()


def rasterize_gsplat(inputs: RenderInputs, config: RasterConfig) -> RenderOutput:
    """``rasterize`` through gsplat (inputs already validated by ``function.validate_inputs``).

    Outputs are on the device of ``means_m``: the GPU's, or copied back to the CPU."""
    gsplat = gsplat_module()
    home = inputs.means_m.device
    dev = home if home.type == "cuda" else torch.device("cuda")
    names = ("means_m", "quats_wxyz", "log_scales", "opacity_logits", "colors", "background")
    means, quats, log_scales, logits, colors, background = (
        getattr(inputs, name).to(dev) for name in names
    )
    k = inputs.K.detach().to(dev, torch.float32).clone()
    k[0, 2] += 0.5  # gsplat samples pixel (u, v) at (u + 0.5, v + 0.5)
    k[1, 2] += 0.5
    vm = inputs.viewmat.detach().to(dev, torch.float32)
    rendered, alphas, meta = gsplat.rasterization(
        means=means,
        quats=quats,
        scales=torch.exp(log_scales),
        opacities=torch.sigmoid(logits),
        colors=colors,
        viewmats=vm[None],
        Ks=k[None],
        width=inputs.width_px,
        height=inputs.height_px,
        near_plane=config.near_m,
        far_plane=config.far_m,
        eps2d=config.eps2d_px2,
        sh_degree=None,
        packed=False,
        tile_size=GSPLAT_TILE_PX,
        backgrounds=background[None],
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    image = rendered[0, ..., :3]
    alpha = alphas[0, ..., 0]
    with torch.no_grad():
        depth = rendered[0, ..., 3].detach()
        depth = torch.where(alpha.detach() >= _DEPTH_ALPHA_MIN, depth, torch.zeros_like(depth))
        radii = meta["radii"][0]
        radii = (radii.amax(dim=-1) if radii.dim() == 2 else radii).to(torch.int32)
    if home.type != "cuda":
        image, alpha, depth, radii = image.to(home), alpha.to(home), depth.to(home), radii.to(home)
    return RenderOutput(image=image, alpha=alpha, depth_m=depth, radii_px=radii)
