"""View refiners on a simulated auxiliary view with ground truth: which GuidedConfig settings help.

    .venv/bin/python bench/bench_refiners.py              # 960x600, 3 cases, 5 timed calls each
    .venv/bin/python bench/bench_refiners.py --quick      # 1 case, 2 timed calls

A case: world seed 11 (intraoperative), the reference is unit 0's left SVGA sensor (distortion
dropped), the auxiliary camera stands ``baseline_m`` beside it looking at the same target. The
sim renders both ideally (truth). The "render" of the auxiliary view imitates a sparse-view
3DGS model after warm-up:
- holes (alpha 0, depth 0): what the reference camera does not see (disocclusions) and random
  blobs where the point cloud had no points;
- sparse blobs (alpha 0.3, the colour composited over black, depth kept);
- everywhere: Gaussian blur (sigma 1.5 px), low-frequency colour blotches (+-0.06), pixel
  noise (sigma 0.02); depth with 0.5 % pixel noise and a 1 % smooth error.
The reference image is the ideal reference render plus noise (sigma 0.01); its depth is the true
one with 0.3 % noise. Prints a Markdown table: PSNR (dB) of the render and of each variant's
output against the auxiliary truth, over all pixels, over the returned mask, over the holes; the
mask's coverage; median ms per call. BENCHMARKS.md ("Refiners") records a run of it.

    .venv/bin/python bench/bench_refiners.py --difix-cost 320x512,576x960

times one call of the Difix adapter's model (``DifixModel.run``) at SD-Turbo's size with random
weights (the real ones cannot be downloaded here; the cost does not depend on the values), with
and without the reference, at each HxW.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from protocol.camera import Camera, Pose
from reconstructor.refine.base import IdentityRefiner, Refiner, RefineRequest
from reconstructor.refine.guided import GuidedConfig, GuidedRefiner


@dataclass(frozen=True)
class Case:
    request: RefineRequest
    truth: np.ndarray  # (H, W, 3) float32 in [0, 1]: the auxiliary view, ideal
    holes: np.ndarray  # (H, W) bool: alpha 0 in the degraded render


def _blobs(shape: tuple[int, int], n: int, r_px: tuple[int, int], rng: np.random.Generator):
    mask = np.zeros(shape, np.uint8)
    for _ in range(n):
        centre = (int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0])))
        axes = (int(rng.integers(*r_px)), int(rng.integers(*r_px)))
        cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return mask > 0


def _smooth_field(shape: tuple[int, int], channels: int, rng: np.random.Generator) -> np.ndarray:
    """Noise in [-1, 1] that varies over ~1/16 of the image."""
    h, w = shape
    small = rng.uniform(-1, 1, (h // 32 + 2, w // 32 + 2, channels)).astype(np.float32)
    big = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(big.reshape(h, w, channels), -1, 1)


def make_case(
    *, seed: int = 11, t_s: float = 1.0, baseline_m: float = 0.3, rng_seed: int = 0, scale=1.0
) -> Case:
    """One reference/auxiliary pair from the sim with a degraded render (module docstring).

    ``scale`` < 1 renders smaller images (faster tests); the cameras' intrinsics scale with it.
    """
    from sim import World

    rng = np.random.default_rng(rng_seed)
    world = World.from_seed(seed, phase="intraoperative")
    sensor = world.unit(0).sensor("left", "SVGA")
    intr = sensor.intrinsics.undistorted()
    if scale != 1.0:
        intr = dataclasses.replace(
            intr,
            width_px=round(intr.width_px * scale),
            height_px=round(intr.height_px * scale),
            fx_px=intr.fx_px * scale,
            fy_px=intr.fy_px * scale,
            cx_px=(intr.cx_px + 0.5) * scale - 0.5,
            cy_px=(intr.cy_px + 0.5) * scale - 0.5,
        )
    ref_cam = Camera(name="reference", intrinsics=intr, pose=sensor.pose)
    ref = world.render(ref_cam, t_s)
    h, w = ref.depth_m.shape
    centre_depth = float(ref.depth_m[h // 2, w // 2])
    eye = ref_cam.pose.centre_m
    target = eye + ref_cam.pose.R[2] * centre_depth
    # sideways, a little down and forward (the rig hangs near the walls): a hemisphere pose
    R = ref_cam.pose.R
    for side in (1.0, -1.0):
        step = side * 0.8 * R[0] + 0.25 * R[1] + 0.55 * R[2]
        aux_eye = eye + baseline_m * step / np.linalg.norm(step)
        if world.config.room.contains(aux_eye, margin_m=0.05):
            break
    aux_cam = Camera(name="auxiliary", intrinsics=intr, pose=Pose.look_at(aux_eye, target))
    aux = world.render(aux_cam, t_s)

    truth = aux.image_rgb.astype(np.float32) / 255.0
    depth = np.where(np.isfinite(aux.depth_m), aux.depth_m, 0).astype(np.float32)
    ref_depth = np.where(np.isfinite(ref.depth_m), ref.depth_m, 0).astype(np.float32)

    # what the reference does not see: disoccluded by the true depths (1 % tolerance)
    vs, us = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(us - intr.cx_px) / intr.fx_px, (vs - intr.cy_px) / intr.fy_px], -1)
    pts_cam = np.concatenate([rays, np.ones((h, w, 1))], -1) * depth[..., None]
    pts_world = (pts_cam.reshape(-1, 3) - aux_cam.pose.t_m) @ aux_cam.pose.R
    in_ref = ref_cam.pose.transform(pts_world)
    z = in_ref[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(intr.fx_px * in_ref[:, 0] / z + intr.cx_px)
        v = np.rint(intr.fy_px * in_ref[:, 1] / z + intr.cy_px)
    ok = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    seen = np.zeros(h * w, bool)
    d_at = ref_depth[v[ok].astype(int), u[ok].astype(int)]
    seen[ok] = np.abs(z[ok] - d_at) < 0.01 * d_at
    unseen = ~seen.reshape(h, w)

    s = w / 960
    holes = unseen | _blobs((h, w), 8, (max(2, int(15 * s)), max(3, int(50 * s))), rng)
    sparse = _blobs((h, w), 8, (max(2, int(15 * s)), max(3, int(50 * s))), rng) & ~holes
    alpha = np.ones((h, w), np.float32)
    alpha[sparse] = 0.3
    alpha[holes] = 0.0

    render = cv2.GaussianBlur(truth, (0, 0), 1.5 * max(s, 0.5))
    render = render + 0.06 * _smooth_field((h, w), 3, rng)
    render = render + rng.normal(0, 0.02, render.shape).astype(np.float32)
    render = np.clip(render, 0, 1) * alpha[..., None]
    noisy_depth = depth * (
        1 + 0.005 * rng.standard_normal((h, w)) + 0.01 * _smooth_field((h, w), 1, rng)[..., 0]
    )
    noisy_depth = np.where(alpha > 0, noisy_depth, 0).astype(np.float32)
    reference = ref.image_rgb.astype(np.float32) / 255.0
    reference = np.clip(reference + rng.normal(0, 0.01, reference.shape), 0, 1)
    ref_model_depth = ref_depth * (1 + 0.003 * rng.standard_normal(ref_depth.shape))
    request = RefineRequest(
        rendered=render.astype(np.float32),
        rendered_alpha=alpha,
        rendered_depth_m=noisy_depth,
        camera=aux_cam,
        reference=reference.astype(np.float32),
        reference_mask=np.ones((h, w), bool),
        reference_depth_m=ref_model_depth.astype(np.float32),
        reference_camera=ref_cam,
    )
    return Case(request=request, truth=truth, holes=holes)


def psnr(a: np.ndarray, b: np.ndarray, where: np.ndarray | None = None) -> float:
    """PSNR in dB of two [0, 1] images, over ``where`` (all pixels when None)."""
    diff = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = float(diff.mean() if where is None else diff[where].mean()) if diff.size else 0.0
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


VARIANTS: dict[str, GuidedConfig] = {
    "defaults": GuidedConfig(),
    "no inpaint": GuidedConfig(use_inpaint=False),
    "guided filter": GuidedConfig(use_guided_filter=True),
    "guided filter, no inpaint": GuidedConfig(use_guided_filter=True, use_inpaint=False),
    "depth_tolerance 0.01": GuidedConfig(depth_tolerance=0.01),
    "depth_tolerance 0.1": GuidedConfig(depth_tolerance=0.1),
    "warp_weight 0.5": GuidedConfig(warp_weight=0.5),
    "warp_weight 0 (render kept)": GuidedConfig(warp_weight=0.0),
    "min_alpha 0.2": GuidedConfig(min_alpha=0.2),
    "inpaint_radius_px 8": GuidedConfig(inpaint_radius_px=8),
    "inpaint_scale 1": GuidedConfig(inpaint_scale=1.0),
    "inpaint_scale 0.5": GuidedConfig(inpaint_scale=0.5),
    "inpaint_scale 0.125": GuidedConfig(inpaint_scale=0.125),
    "depth_tolerance 0.05": GuidedConfig(depth_tolerance=0.05),
    "guided filter, seam_band_px 1": GuidedConfig(use_guided_filter=True, seam_band_px=1),
    "guided filter, seam_band_px 8": GuidedConfig(use_guided_filter=True, seam_band_px=8),
    "guided filter, radius 8": GuidedConfig(use_guided_filter=True, guided_filter_radius_px=8),
    "guided filter, eps 1e-4": GuidedConfig(use_guided_filter=True, guided_filter_eps=1e-4),
    "guided filter, eps 1e-2": GuidedConfig(use_guided_filter=True, guided_filter_eps=1e-2),
    "supervise_inpainted": GuidedConfig(supervise_inpainted=True),
}


def run(
    cases: list[Case], repeats: int
) -> list[tuple[str, float, float, float, float, float, float]]:
    refiners: list[tuple[str, Refiner]] = [("render (none)", IdentityRefiner())]
    refiners += [(name, GuidedRefiner(cfg)) for name, cfg in VARIANTS.items()]
    rows = []
    for name, refiner in refiners:
        all_db, mask_db, hole_db, cover, times, cpu = [], [], [], [], [], []
        for case in cases:
            out = refiner.refine(case.request)
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                refiner.refine(case.request)
                times.append((time.perf_counter() - t0) * 1e3)
                cpu.append((time.process_time() - c0) * 1e3)
            all_db.append(psnr(out.image, case.truth))
            mask_db.append(psnr(out.image, case.truth, out.mask))
            hole_db.append(psnr(out.image, case.truth, case.holes))
            cover.append(float(out.mask.mean()))
        rows.append(
            (
                name,
                statistics.mean(all_db),
                statistics.mean(mask_db),
                statistics.mean(hole_db),
                statistics.mean(cover),
                statistics.median(times),
                statistics.median(cpu),
            )
        )
    return rows


def difix_cost(sizes_hw: list[tuple[int, int]]) -> None:
    """Print the wall and CPU time of one Difix call at SD-Turbo's size (random weights)."""
    import torch
    from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel

    from reconstructor.refine.difix import NUM_VIEWS, DifixModel, set_frame_attention

    t0 = time.perf_counter()
    vae: Any = AutoencoderKL(  # SD-Turbo's VAE (SD 2.1)
        block_out_channels=(128, 256, 512, 512),
        layers_per_block=2,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        latent_channels=4,
        sample_size=512,
    )
    unet: Any = UNet2DConditionModel(  # SD-Turbo's UNet (SD 2.1)
        sample_size=64,
        block_out_channels=(320, 640, 1280, 1280),
        attention_head_dim=(5, 10, 20, 20),
        cross_attention_dim=1024,
        use_linear_projection=True,
        layers_per_block=2,
    )
    vae.eval()
    unet.eval()
    skips = torch.nn.ModuleList(
        torch.nn.Conv2d(i, o, 1, bias=False)
        for i, o in [(512, 512), (256, 512), (128, 512), (128, 256)]
    )
    set_frame_attention(unet, NUM_VIEWS)
    sched: Any = DDPMScheduler(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012)
    model = DifixModel(
        vae=vae,
        unet=unet,
        skip_convs=skips,
        prompt_embeds=torch.zeros(1, 77, 1024),
        alphas_cumprod=sched.alphas_cumprod.double(),
        prediction_type="epsilon",
        size_multiple=64,
    )
    n_unet = sum(p.numel() for p in unet.parameters()) / 1e6
    print(
        f"built in {time.perf_counter() - t0:.0f} s: UNet {n_unet:.0f} M parameters, "
        f"torch threads {torch.get_num_threads()}"
    )
    print("| size (HxW) | reference | wall s/call | CPU s/call |")
    print("|---|---|---:|---:|")
    for h, w in sizes_hw:
        x = torch.rand(1, 3, h, w) * 2 - 1
        for ref in (None, x.clone()):
            t0, c0 = time.perf_counter(), time.process_time()
            with torch.inference_mode():
                model.run(x, ref, 199)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            print(f"| {h}x{w} | {'yes' if ref is not None else 'no'} | {wall:.1f} | {cpu:.1f} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one case, 2 timed calls")
    parser.add_argument(
        "--difix-cost",
        metavar="HxW,...",
        help="instead: time the Difix model at SD-Turbo size at these sizes (multiples of 64)",
    )
    args = parser.parse_args(argv)
    if args.difix_cost:
        sizes = [tuple(int(v) for v in s.split("x")) for s in args.difix_cost.split(",")]
        difix_cost([(h, w) for h, w in sizes])
        return
    specs = [(0.3, 0, 1.0)] if args.quick else [(0.2, 0, 1.0), (0.3, 1, 2.0), (0.4, 2, 3.0)]
    cases = [make_case(baseline_m=b, rng_seed=r, t_s=t) for b, r, t in specs]
    repeats = 2 if args.quick else 5
    for case in cases:
        alpha = case.request.rendered_alpha
        print(
            f"case: {case.truth.shape[1]}x{case.truth.shape[0]}, holes "
            f"{100 * case.holes.mean():.1f} %, sparse (alpha 0.3) "
            f"{100 * ((alpha > 0) & (alpha < 1)).mean():.1f} %"
        )
    rows = run(cases, repeats)
    print()
    print(
        "| refiner | PSNR all (dB) | PSNR in mask (dB) | PSNR holes (dB) | mask (%) "
        "| wall ms/call | CPU ms/call |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, a, m, hdb, cov, ms, cpu_ms in rows:
        print(
            f"| {name} | {a:.2f} | {m:.2f} | {hdb:.2f} | {100 * cov:.1f} | {ms:.1f} "
            f"| {cpu_ms:.1f} |"
        )


if __name__ == "__main__":
    main()
