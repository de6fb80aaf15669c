"""Per-frame wand detection (detect + label + refit without the rod): cost and accuracy.

    .venv/bin/python bench/bench_wand_detect.py                    # builds /tmp/detcache once
    .venv/bin/python bench/bench_wand_detect.py --cache DIR --repeat 3

Frames: ``World.from_seed(5, phase="wand")``, units 0 and 2, both sensors, HD1200, 25 times
in 3.3-29.7 s, JPEG-encoded the way wand sessions store them (quality 92, 4:4:4) and decoded:
what calibration sees. The background of each sensor is the median of its frames at 3, 9, 15,
21 and 27 s. Rendering all of it takes about half a minute; the JPEG bytes and the truth (projected
sphere centres, and which spheres are whole and unoccluded) are cached in ``--cache``.

Per frame, single thread (``cv2.setNumThreads(1)``), what ``calibration.detect.extract`` does::

    label = refit_without_rod(det, image, label_wand(det.detect(image), wand))

timed for the reference path (``DetectorConfig(kernels="numpy")``: the numpy twins of the
kernels, i.e. the code as it was, to the bit) and the default (numba) path, frame by frame in
turn, best of ``--repeat`` runs each. Prints a Markdown table: ms per image, labelled frames,
centre error against the truth (labelled spheres that are whole in the image, and all labelled
spheres) and how far the default path's final centres lie from the reference path's; and the
default path's first call in the process (numba compiling its kernels, about 10 s, or loading
them from the cache next to calibration/detect/kernels.py, well under a second).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

UNITS = (0, 2)
SIDES = ("left", "right")
TIMES = tuple(float(t) for t in np.round(np.linspace(3.3, 29.7, 25), 3))
BACKGROUND_T = (3.0, 9.0, 15.0, 21.0, 27.0)
JPEG_PARAMS = [
    int(cv2.IMWRITE_JPEG_QUALITY),
    92,
    int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR),
    int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
]


def _encode(image_rgb: np.ndarray) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(image_rgb[:, :, ::-1]), JPEG_PARAMS)
    assert ok
    return np.frombuffer(buf.tobytes(), np.uint8)


def build_cache(cache: Path) -> None:
    """Render the frames and store them (JPEG) with the truth, one .npz per sensor."""
    from sim import World
    from sim.truth import wand_sphere_whole

    world = World.from_seed(5, phase="wand")
    cache.mkdir(parents=True, exist_ok=True)
    for unit in UNITS:
        for side in SIDES:
            out = cache / f"unit{unit}_{side}.npz"
            if out.exists():
                continue
            t0 = time.perf_counter()
            cam = world.rig[unit].sensor(side, "HD1200")
            bg = [_encode(world.render_sensor(unit, side, t).image_rgb) for t in BACKGROUND_T]
            jpegs, truth, whole = [], [], []
            for t in TIMES:
                r = world.render_sensor(unit, side, t)
                centres = world.wand_centres(t)
                assert centres is not None
                px, _ = cam.project(centres)
                jpegs.append(_encode(r.image_rgb))
                truth.append(px)
                whole.append([wand_sphere_whole(world, r, t, k) for k in range(3)])
            arrays: dict[str, np.ndarray] = {f"bg{i}": b for i, b in enumerate(bg)}
            arrays.update({f"frame{i}": j for i, j in enumerate(jpegs)})
            arrays.update(
                times=np.array(TIMES),
                truth=np.array(truth),
                whole=np.array(whole),
                n_bg=np.array(len(bg)),
            )
            np.savez(out, **arrays)  # type: ignore[arg-type]
            print(f"cached {out.name} in {time.perf_counter() - t0:.0f} s", flush=True)


def load_cache(cache: Path) -> dict[tuple[int, str], dict]:
    out = {}
    for unit in UNITS:
        for side in SIDES:
            z = np.load(cache / f"unit{unit}_{side}.npz")
            dec = lambda a: cv2.imdecode(a, cv2.IMREAD_COLOR)  # noqa: E731
            out[(unit, side)] = {
                "background": [dec(z[f"bg{i}"]) for i in range(int(z["n_bg"]))],
                "frames": [dec(z[f"frame{i}"]) for i in range(len(z["times"]))],
                "truth": z["truth"],
                "whole": z["whole"],
            }
    return out


def _pipeline(det, image: np.ndarray, wand) -> tuple[np.ndarray | None, float]:
    from calibration.detect.label import label_wand, refit_without_rod

    t0 = time.perf_counter()
    label = refit_without_rod(det, image, label_wand(det.detect(image), wand))
    return label.points_px, time.perf_counter() - t0


def _stats(errors: list[float]) -> str:
    if not errors:
        return "-"
    e = np.asarray(errors)
    return f"{np.median(e):.3f} / {np.percentile(e, 95):.3f} / {e.max():.3f}"


def run(cache: Path, repeat: int) -> None:
    from calibration.detect.config import DetectorConfig
    from calibration.detect.detector import SphereDetector
    from protocol.formats.wand import WandSpec
    from sim import World

    cv2.setNumThreads(1)
    world = World.from_seed(5, phase="wand")
    wand = WandSpec()
    data = load_cache(cache)
    paths = {"reference (numpy)": DetectorConfig(kernels="numpy"), "numba": DetectorConfig()}
    ms: dict[str, list[float]] = {p: [] for p in paths}
    points: dict[str, list[np.ndarray | None]] = {p: [] for p in paths}
    whole_err: dict[str, list[float]] = {p: [] for p in paths}
    all_err: dict[str, list[float]] = {p: [] for p in paths}
    first_call_ms = math.nan
    for (unit, side), d in data.items():
        intr = world.rig[unit].sensor(side, "HD1200").intrinsics
        dets = {}
        for name, cfg in paths.items():
            dets[name] = SphereDetector(intr, wand.radius_m, cfg)
            dets[name].fit_background(d["background"])
            if math.isnan(first_call_ms) and cfg.kernels == "numba":
                # compiling (or loading the cached) kernels, the colour table: once a process
                first_call_ms = 1000 * _pipeline(dets[name], d["frames"][0], wand)[1]
        for i, image in enumerate(d["frames"]):
            best: dict[str, float] = {}
            for _ in range(repeat):  # the paths in turn, so both see the same machine load
                for name, det in dets.items():
                    pts, dt = _pipeline(det, image, wand)
                    best[name] = min(best.get(name, math.inf), dt)
            for name in paths:
                ms[name].append(1000 * best[name])
                points[name].append(pts := _pipeline(dets[name], image, wand)[0])
                if pts is None:
                    continue
                err = np.linalg.norm(pts - d["truth"][i], axis=1)
                all_err[name].extend(err.tolist())
                whole_err[name].extend(err[d["whole"][i]].tolist())
    ref_name = next(iter(paths))
    print(f"{len(ms[ref_name])} HD1200 frames (JPEG q92 4:4:4), best of {repeat} per frame, ")
    print(f"one thread; the numba path's first call in a process: {first_call_ms:.0f} ms\n")
    print(
        "| path | ms per image (median) | mean | labelled frames | centre error, whole "
        "spheres (median / p95 / max px) | all labelled spheres | vs reference (median / max "
        "px) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in paths:
        agree = [
            float(np.linalg.norm(a - b, axis=1).max())
            for a, b in zip(points[name], points[ref_name], strict=True)
            if a is not None and b is not None
        ]
        n_lab = sum(p is not None for p in points[name])
        ratio = np.median(ms[ref_name]) / np.median(ms[name])
        print(
            f"| {name} | {np.median(ms[name]):.1f} ({ratio:.2f}x) | {np.mean(ms[name]):.1f} | "
            f"{n_lab} of {len(points[name])} | {_stats(whole_err[name])} "
            f"({len(whole_err[name])}) | {_stats(all_err[name])} ({len(all_err[name])}) | "
            f"{np.median(agree):.1e} / {max(agree):.1e} |"
        )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cache", type=Path, default=Path("/tmp/detcache"))
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per frame and path")
    parser.add_argument("--build-only", action="store_true", help="render and cache, no timing")
    args = parser.parse_args()
    build_cache(args.cache)
    if not args.build_only:
        run(args.cache, args.repeat)
