"""A wand session's views: where the moving objects are ray-cast (``sim.render.moving_region``)
against the path before, in the same run, on the frames the calibration test and the demo
prerender.

    .venv/bin/python bench/bench_sim_region.py [--step-s 1.0] [--seeds 0 5]

The path before bounded each moving mesh by its projected pixel box and cast every pixel
(``None``) when a mesh reached beside or behind a camera or when the lens folded its projection;
today's keeps, inside that box, the pixels whose rays fall in the box the mesh's vertices span
in normalized image coordinates, and bounds a mesh beside the camera by its bounding sphere. For
every frame both renders must be equal, pixel for pixel. Prints a Markdown table (CPU seconds of
this process, so other jobs on the machine change the numbers less than wall time would).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def pixel_box_region(camera, meshes: list, margin_px: int = 3) -> np.ndarray | None:
    """The region before: the union of the meshes' projected pixel boxes; None (every pixel)
    when a mesh reaches behind or beside the camera or its projection is folded by the lens."""
    intr = camera.intrinsics
    H, W = intr.height_px, intr.width_px
    mask = np.zeros((H, W), bool)
    for mesh in meshes:
        v = mesh.vertices.astype(np.float64)
        if len(v) == 0:
            continue
        z = v @ camera.pose.R[2] + camera.pose.t_m[2]
        if z.min() < 0.05:
            if z.max() < 0.05:
                continue
            return None
        px, _ = camera.project(v)
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - margin_px
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + margin_px
        if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
            continue
        if u0 < -W or v0 < -H or u1 > 2 * W or v1 > 2 * H:
            return None
        mask[max(v0, 0) : min(v1, H - 1) + 1, max(u0, 0) : min(u1, W - 1) + 1] = True
    return np.flatnonzero(mask)


def _views(
    seed: int, loop_s: float, step_s: float
) -> tuple[int, dict[str, tuple[float, int, int]]]:
    """The number of views, and for each path: CPU seconds and rays cast per view, and the views
    it cast whole."""
    from sim import World
    from sim.render import moving_region, render_over_background

    world = World.from_seed(seed, phase="wand")
    cams = [world.sensor(u, "left", "HD1200") for u in range(len(world.rig))]
    times = np.arange(0.0, loop_s, step_s)
    n_static = len(world.static_objects)
    for c in cams:
        world._render_view(c, 0.0)  # warm: ray tables, backgrounds, JIT
    paths = {"ray-space boxes (today)": moving_region, "pixel boxes (before)": pixel_box_region}
    cpu = dict.fromkeys(paths, 0.0)
    rays = dict.fromkeys(paths, 0)
    whole = dict.fromkeys(paths, 0)
    for t in times:
        moving = world._moving_cache(float(t))
        meshes = [o.mesh for o in moving.objects]
        for c in cams:
            images = []
            for name, region_fn in paths.items():
                c0 = time.process_time()
                region = region_fn(c, meshes)
                img = render_over_background(moving, c, world._background(c), n_static, region)
                cpu[name] += time.process_time() - c0
                n = c.intrinsics.width_px * c.intrinsics.height_px
                rays[name] += n if region is None else len(region)
                whole[name] += region is None
                images.append(img)
            a, b = images
            for x, y in ((a.radiance, b.radiance), (a.depth_m, b.depth_m)):
                np.testing.assert_array_equal(x, y, err_msg=f"seed {seed} {c.name} t={t}")
            np.testing.assert_array_equal(a.object_index, b.object_index)
    views = len(times) * len(cams)
    return views, {k: (cpu[k] / views, rays[k] // views, whole[k]) for k in paths}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--step-s", type=float, default=1.0, help="time between frames")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 5])
    args = parser.parse_args()
    # the demo's stage 3 loops 33 s of seed 0, the calibration test 27 s of seed 5
    loops = {0: 33.0, 5: 27.0}
    print("| seed, views | region | CPU per view (ms) | rays per view | cast whole | vs before |")
    print("|---|---|---:|---:|---:|---|")
    for seed in args.seeds:
        views, out = _views(seed, loops.get(seed, 27.0), args.step_s)
        before = out["pixel boxes (before)"][0]
        for name, (cpu_s, rays, whole) in out.items():
            note = "reference" if "before" in name else f"{before / cpu_s:.2f}x less CPU"
            print(
                f"| {seed}, {views} HD1200 views | {name} | {1000 * cpu_s:.1f} | {rays:,} | "
                f"{whole} | {note} |"
            )
    print("every view: the two renders equal, pixel for pixel (radiance, depth, object index)")


if __name__ == "__main__":
    main()
