"""A sim timestamp as posed views and a truth-depth init, shared by the GPU backend's tests
(tests/reconstructor/test_gsplat_train.py) and benchmark (bench/bench_gpu.py).

No stereo and no fusion: open3d is not on the GPU machine, and both backends must start from the
very same Gaussians. The init is what a perfect stereo init would give: one Gaussian per
``stride_px``-th pixel of each training camera's true depth, coloured by its true pixel.
Training views are the rig's left sensors; held out are its right sensors (the paper's
near-field protocol), all at SVGA (960 x 600), the size the paper trains at.

The sim ray-casts with open3d, which the GPU machine lacks: ``save_scene`` writes the scene (and
the training cameras' views one second later, for a warm start) to an ``.npz`` here, and
``scene_for_gpu`` loads it there when ``$EGOSURG_GPU_SCENE`` names it. Images are the sim's
uint8 pixels, so the file holds exactly the views the sim gives.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from protocol.camera import Camera, Intrinsics
from reconstructor.data.views import View, view_from_image
from reconstructor.splats.gaussians import Gaussians, init_from_points
from reconstructor.splats.train import scene_extent_m

SVGA_PX = (960, 600)


@dataclass
class SimScene:
    train: list[View]
    held_out: list[View]
    gaussians: Gaussians
    extent_m: float


def _views(world, cams: list[Camera], t_s: float) -> tuple[list[View], list]:
    renders = [world.render(c, t_s) for c in cams]
    return [view_from_image(c, r.image_rgb) for c, r in zip(cams, renders, strict=True)], renders


def sim_scene(
    world, t_s: float, size_px: tuple[int, int] = SVGA_PX, stride_px: int = 4,
    hfov_deg: float = 100.0,
) -> SimScene:  # fmt: skip
    """The rig at ``t_s``: left sensors to train on, right sensors held out, and Gaussians from
    the training cameras' true depth."""
    intr = Intrinsics.from_fov(size_px[0], size_px[1], hfov_deg)
    left = [
        Camera(name=f"u{i}-left", intrinsics=intr, pose=u.left_pose)
        for i, u in enumerate(world.rig)
    ]
    right = [
        Camera(name=f"u{i}-right", intrinsics=intr, pose=u.right_pose())
        for i, u in enumerate(world.rig)
    ]
    train, renders = _views(world, left, t_s)
    held_out, _ = _views(world, right, t_s)
    pts, cols = [], []
    k_inv = np.linalg.inv(intr.K)
    for c, r in zip(left, renders, strict=True):
        v, u = np.mgrid[0 : size_px[1] : stride_px, 0 : size_px[0] : stride_px]
        z = r.depth_m[v, u]
        hit = np.isfinite(z) & (z > 0)
        rays = k_inv @ np.stack([u[hit], v[hit], np.ones(hit.sum())])
        pts.append(((rays * z[hit]).T - c.pose.t_m) @ c.pose.R)
        cols.append(r.image_rgb[v[hit], u[hit]] / 255.0)
    gaussians = init_from_points(np.concatenate(pts), np.concatenate(cols))
    return SimScene(train, held_out, gaussians, scene_extent_m(train))


def next_views(world, scene: SimScene, t_s: float) -> list[View]:
    """The same training cameras at another time (a warm-started timestamp's views)."""
    cams = [v.camera for v in scene.train]
    return _views(world, cams, t_s)[0]


SCENE_ENV = "EGOSURG_GPU_SCENE"
WORLD_SEED, T_S, LATER_T_S = 11, 1.0, 2.0  # the tests' intraoperative world (tests/conftest.py)


def build(world=None) -> tuple[SimScene, list[View]]:
    """The scene at ``T_S`` and its training cameras' views at ``LATER_T_S``, from the sim."""
    if world is None:
        from sim import World

        world = World.from_seed(WORLD_SEED, phase="intraoperative")
    scene = sim_scene(world, T_S)
    return scene, next_views(world, scene, LATER_T_S)


def save_scene(path: Path, scene: SimScene, later: list[View]) -> None:
    arrays: dict[str, np.ndarray] = {}
    for group, views in (("train", scene.train), ("held_out", scene.held_out), ("later", later)):
        for k, v in enumerate(views):
            arrays[f"{group}{k}_image"] = (v.image.numpy() * 255 + 0.5).astype(np.uint8)
            arrays[f"{group}{k}_mask"] = (v.mask.numpy() > 0.5).astype(np.uint8)
            arrays[f"{group}{k}_viewmat"] = v.viewmat.numpy()
            arrays[f"{group}{k}_K"] = v.K.numpy()
            arrays[f"{group}{k}_name"] = np.array(v.name)
    for f in fields(scene.gaussians):
        arrays[f"g_{f.name}"] = getattr(scene.gaussians, f.name).detach().numpy()
    arrays["extent_m"] = np.array(scene.extent_m)
    np.savez_compressed(path, **arrays)  # type: ignore[arg-type]  # numpy's stub: allow_pickle


def load_scene(path: Path) -> tuple[SimScene, list[View]]:
    with np.load(path) as z:

        def views(group: str) -> list[View]:
            out, k = [], 0
            while f"{group}{k}_image" in z:
                img = z[f"{group}{k}_image"]
                out.append(View(
                    name=str(z[f"{group}{k}_name"]),
                    image=torch.from_numpy(img.astype(np.float32) / 255.0),
                    mask=torch.from_numpy(z[f"{group}{k}_mask"].astype(np.float32)),
                    viewmat=torch.from_numpy(z[f"{group}{k}_viewmat"]),
                    K=torch.from_numpy(z[f"{group}{k}_K"]),
                    width_px=img.shape[1], height_px=img.shape[0],
                ))  # fmt: skip
                k += 1
            return out

        g = Gaussians(**{f.name: torch.from_numpy(z[f"g_{f.name}"]) for f in fields(Gaussians)})
        scene = SimScene(views("train"), views("held_out"), g, float(z["extent_m"]))
        return scene, views("later")


def scene_for_gpu() -> tuple[SimScene, list[View]]:
    """The saved scene where ``$EGOSURG_GPU_SCENE`` names one (the GPU machine), else the sim's."""
    saved = os.environ.get(SCENE_ENV)
    return load_scene(Path(saved)) if saved else build()


if __name__ == "__main__":  # python -m tests.gpu_scene OUT.npz: the file the GPU machine loads
    import sys

    out = Path(sys.argv[1])
    scene, later = build()
    save_scene(out, scene, later)
    back, _ = load_scene(out)
    assert all(torch.equal(a.image, b.image) for a, b in zip(scene.train, back.train, strict=True))
    print(f"{out}: {out.stat().st_size / 1e6:.1f} MB, {scene.gaussians.num} Gaussians")
