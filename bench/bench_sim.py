"""Simulator speed: one stereo pair at each ZED X mode, and the compiled kernels against their
numpy twins on the same inputs, in the same run.

    .venv/bin/python bench/bench_sim.py [--repeats 5]

Prints a Markdown table; BENCHMARKS.md records a run of it.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def _best(fn, repeats: int) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    from sim import World
    from sim.render import ray_directions, render_view, shade_reference
    from sim.sensor import SensorSpec, expose, expose_reference

    world = World.from_seed(0, phase="intraoperative")
    rows = []
    for res in ("HD1200", "HD1080", "SVGA"):
        world.render_stereo(0, 1.0, res)  # warm: ray tables, JIT
        k = iter(range(1000))
        best, med = _best(
            lambda k=k, res=res: world.render_stereo(0, 1.0 + 0.01 * next(k), res), args.repeats
        )
        rows.append((f"stereo pair {res} (scene build + 2 x cast + shade + sensor)", best, med, ""))

    cam = world.sensor(0, "left", "HD1200")
    scene = world.scene_at(2.0)
    img = render_view(scene, cam)
    for phase in ("intraoperative", "wand"):
        w = World.from_seed(0, phase=phase)
        c = w.sensor(1, "left", "HD1200")
        w._render_view(c, 5.0)  # warm the background cache
        full = _best(lambda w=w, c=c: render_view(w.scene_at(5.0), c), args.repeats)
        fast = _best(lambda w=w, c=c: w._render_view(c, 5.0), args.repeats)
        rows.append(
            (
                f"one HD1200 view, {phase}: cast only where things move",
                *fast,
                f"{full[0] / fast[0]:.1f}x faster",
            )
        )
        rows.append((f"one HD1200 view, {phase}: cast every pixel", *full, "reference"))
    rows += _wand_rows(args.repeats)
    best, med = _best(lambda: world._build_scene(2.0 + 1e-6 * time.perf_counter()), args.repeats)
    rows.append(("scene build at one instant (meshes + BVH)", best, med, ""))
    from sim import kernels

    rays = kernels.make_rays(
        ray_directions(cam.intrinsics).reshape(-1, 3),
        cam.pose.R.astype(np.float32),
        cam.pose.centre_m.astype(np.float32),
    )
    best_cast, med_cast = _best(lambda: scene.cast_rays(rays), args.repeats)
    rows.append(("open3d cast_rays, 1920x1200", best_cast, med_cast, ""))

    t, obj, normals = scene.cast_rays(rays)
    fast = _best(
        lambda: kernels.shade_pixels(
            rays,
            t,
            obj,
            normals,
            scene.obj_R,
            scene.obj_t,
            scene.obj_tex,
            scene.obj_tint,
            scene.obj_emission,
            scene.texture_stack,
            scene.texel_m,
            scene.light_pos,
            scene.light_power,
            0.14,
        ),
        args.repeats,
    )
    valid = obj >= 0
    pts = rays[valid, :3] + rays[valid, 3:] * t[valid, None]
    nrm = normals[valid].copy()
    nrm[np.einsum("ij,ij->i", nrm, rays[valid, 3:]) > 0] *= -1
    slow = _best(lambda: shade_reference(scene, pts, nrm, obj[valid]), max(2, args.repeats // 2))
    rows.append(("shade 1920x1200: numba kernel", *fast, f"{slow[0] / fast[0]:.1f}x faster"))
    rows.append(("shade 1920x1200: numpy twin", *slow, "reference"))

    spec = SensorSpec()
    fast = _best(lambda: expose(img.radiance, cam.intrinsics, spec, 7), args.repeats)
    slow = _best(lambda: expose_reference(img.radiance, cam.intrinsics, spec, 7), 2)
    rows.append(("sensor 1920x1200: numba kernel", *fast, f"{slow[0] / fast[0]:.1f}x faster"))
    rows.append(("sensor 1920x1200: numpy twin", *slow, "reference"))

    print("| stage | best (s) | median (s) | vs twin |")
    print("|---|---:|---:|---|")
    for name, best, med, note in rows:
        print(f"| {name} | {best:.3f} | {med:.3f} | {note} |")


def _wand_rows(repeats: int) -> list[tuple[str, float, float, str]]:
    """A wand session's frames (what the calibration test and the demo prerender): the moving
    operator and wand over the cached room, against casting the region into the whole room's
    BVH (the path before), and the spheres against their whole-box reference twin."""
    from sim import World
    from sim.render import moving_region, render_view
    from sim.spheres import composite_spheres, composite_spheres_reference

    w = World.from_seed(5, phase="wand")
    cams = [w.sensor(u, "left", "HD1200") for u in range(4)]
    times = [2.5 + 0.9 * i for i in range(24)]
    for c in cams:
        w._render_view(c, 2.5)  # warm: ray tables, backgrounds, JIT

    def frames(fn) -> None:
        for t in times:
            for c in cams:
                fn(c, t)

    def one_scene(c, t) -> None:  # the previous fast path: region cast into room + movers
        scene = w.scene_at(t)
        region = moving_region(c, [o.mesh for o in scene.objects[len(w.static_objects) :]])
        render_view(scene, c, w._background(c) if region is not None else None, region)

    def spheres(composite):
        def run(c, t) -> None:
            bg, m = w._background(c), w._moving_cache(t)
            img = [bg.radiance.copy(), bg.depth_m.copy(), bg.object_index.copy()]
            composite(m.spheres, m.lights, c, *img)

        return run

    n = len(times) * len(cams)
    per = [
        _best(lambda fn=fn: frames(fn), repeats)
        for fn in (
            w._render_view,
            one_scene,
            spheres(composite_spheres),
            spheres(composite_spheres_reference),
        )
    ]
    per = [(b / n, m / n) for b, m in per]
    return [
        (
            "wand session, one HD1200 view: movers over the room",
            *per[0],
            f"{per[1][0] / per[0][0]:.1f}x faster",
        ),
        ("wand session, one HD1200 view: region cast into the whole room", *per[1], "before"),
        (
            "wand spheres, one HD1200 view: where they reach",
            *per[2],
            f"{per[3][0] / per[2][0]:.1f}x faster",
        ),
        ("wand spheres, one HD1200 view: whole box (twin)", *per[3], "reference"),
    ]


if __name__ == "__main__":
    main()
