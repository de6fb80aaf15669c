"""Stereo depth against the sim's true depth: our SGBM+WLS matcher with each check changed one at
a time, with the fill stage that follows it, beside OpenCV's textbook SGBM+WLS on the same
rectified frames, per phase and per camera.

    nice -n 10 .venv/bin/python bench/bench_stereo.py [--seed 11] [--t-s 1.0] \\
        [--phases empty,setup,intraoperative,turnover] [--jpeg-quality 90] [--per-camera NAME]

The frames are the sim's noisy sensor images through the agents' JPEG encoding (quality 90, as
recorded; 0 for raw). For every (phase, camera, matcher): ``density`` is the share of the
rectified left image (pixels that came from inside the sensor) with a depth; ``textured`` and
``blank`` the same over the sim's textured materials (floor, people, instruments) and over its
blank walls and ceiling, from the sim's object labels; ``>1 % / >3 % / >5 %`` are the shares of
the depths more than 1, 3 or 5 % off the sim's true depth along the same ray (pixels on a true
depth edge, where the four truth neighbours differ by more than 1 %, are left out of the error,
as in tests/reconstructor/test_stereo.py); ``right`` and ``centre`` are the densities of the
right-most 120 columns and of the central 120, and ``tex`` the same over textured pixels only
(the right edge sees more blank wall than the centre in the sim). The rows "+ fill" add the
pipeline's fill stage (``reconstructor/depth/fill.py`` at stride 1): "image" spreads confident
disparity along colour edges, "+ shell" also puts what is still a hole on the room's box (the site's
``room_bounds_m``).
Prints Markdown tables: the mean over the cameras per phase, then every camera for the matchers
named by ``--per-camera``. EVALUATION.md ("Stereo depth against the sim's truth") records a run.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import statistics
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from protocol.camera import Camera, Pose
from reconstructor.depth.fill import FillConfig, fill_disparity, fill_points_in_world
from reconstructor.depth.matcher import StereoMatcher
from reconstructor.depth.sgbm import RawDisparities, SgbmWlsMatcher
from reconstructor.depth.stereo import DepthMap, compute_depth, rectifier
from reconstructor.depth.stereo_config import StereoConfig

EDGE_COLUMNS = 120
TEXTURED = ("floor", "scrubs", "skin", "cap", "mask", "shoes", "tray", "steel", "rubber")
BLANK = ("walls", "ceiling")
COLUMNS = (
    "density", "textured", "blank", ">1%", ">3%", ">5%", "right", "centre", "right tex",
    "centre tex",
)  # fmt: skip


class TextbookSgbmWls(StereoMatcher):
    """OpenCV's textbook SGBM+WLS (the ximgproc disparity-filtering sample with these
    numbers): block 5, P1/P2 = 8/32 x 3 x 25, uniqueness 10, speckle 100/2, WLS lambda 8000 and
    sigma 1.5, no padding and no checks beyond SGBM's own; the filtered map wherever it is in
    range."""

    name = "textbook"
    needs_weights = False

    def match(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        min_d = max(0, math.floor(min_disparity_px) - 1)
        num_d = 16 * math.ceil((math.ceil(max_disparity_px) + 1 - min_d) / 16)
        left = cv2.StereoSGBM.create(
            minDisparity=min_d,
            numDisparities=num_d,
            blockSize=5,
            P1=8 * 3 * 25,
            P2=32 * 3 * 25,
            uniquenessRatio=10,
            speckleWindowSize=100,
            speckleRange=2,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
        right = cv2.ximgproc.createRightMatcher(left)
        wls = cv2.ximgproc.createDisparityWLSFilter(left)
        wls.setLambda(8000.0)
        wls.setSigmaColor(1.5)
        dl, dr = left.compute(left_rgb, right_rgb), right.compute(right_rgb, left_rgb)
        out = wls.filter(dl, left_rgb, disparity_map_right=dr).astype(np.float32) / 16.0
        out[(out < min_d) | (out > min_d + num_d - 1)] = np.nan
        return out


_RAW_CACHE: dict[tuple, RawDisparities] = {}
# the fields that change SGBM's or WLS's output; the others only change which pixels are kept
_MATCHING_FIELDS = (
    "block_size_px", "uniqueness_ratio", "speckle_window_px", "speckle_range_px", "wls_lambda",
    "wls_sigma_color",
)  # fmt: skip


class CachedSgbm(SgbmWlsMatcher):
    """Our matcher, with one SGBM+WLS run shared by every row that changes only the checks."""

    def raw_disparities(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        key = (
            hashlib.blake2b(left_rgb.tobytes(), digest_size=16).digest(),
            min_disparity_px,
            max_disparity_px,
            tuple(getattr(self.config, f) for f in _MATCHING_FIELDS),
        )
        if key not in _RAW_CACHE:
            if len(_RAW_CACHE) > 16:
                _RAW_CACHE.clear()
            _RAW_CACHE[key] = super().raw_disparities(
                left_rgb,
                right_rgb,
                min_disparity_px=min_disparity_px,
                max_disparity_px=max_disparity_px,
            )
        return _RAW_CACHE[key]


@dataclass(frozen=True)
class Row:
    config: StereoConfig | None  # None: the textbook matcher
    fill: str = ""  # "", "image" or "shell"
    # builds the matcher from the row's config (bench/bench_stereo_real.py's variants); None: ours
    matcher: Callable[[StereoConfig], StereoMatcher] | None = None

    def matcher_for(self, cfg0: StereoConfig) -> tuple[StereoConfig, StereoMatcher]:
        """The config (at ``cfg0``'s match scale) and matcher this row runs."""
        if self.config is None:
            return cfg0, TextbookSgbmWls()
        cfg = replace(self.config, match_scale=cfg0.match_scale)
        return cfg, (self.matcher or CachedSgbm)(cfg)


OLD = "before the retune (ZNCC 0.5, WLS 0.5 px)"
BOTH = "ZNCC 0.3 + WLS agreement 1.0 px (measured, not adopted)"
NEW = "ours (the defaults)"


def rows(base: StereoConfig) -> dict[str, Row]:
    """Each row: one change from the checks before the retune (``old``), the defaults
    (``base``), then the fill stage, then the textbook."""
    r = replace
    old = r(base, min_zncc=0.5, wls_max_change_px=0.5)
    return {
        OLD: Row(old),
        "ZNCC check off": Row(r(old, min_zncc=-1.0)),
        "min ZNCC 0.3": Row(r(old, min_zncc=0.3)),
        "WLS agreement 1.0 px": Row(r(old, wls_max_change_px=1.0)),
        "WLS agreement off": Row(r(old, wls_max_change_px=1e3)),
        "left-right 2 px": Row(r(old, lr_max_diff_px=2.0)),
        "uniqueness 5": Row(r(old, uniqueness_ratio=5)),
        "speckle filter off": Row(r(old, speckle_window_px=0)),
        BOTH: Row(r(old, min_zncc=0.3, wls_max_change_px=1.0)),
        NEW: Row(base),
        "before the retune + fill (image)": Row(old, "image"),
        "before the retune + fill (image + shell)": Row(old, "shell"),
        "ours + fill (image + shell)": Row(base, "shell"),
        "textbook SGBM+WLS": Row(None),
    }


def with_fill(depth: DepthMap, cfg: StereoConfig, kind: str, left_pose: Pose, room_box) -> DepthMap:
    """``depth`` with the fill stage's pixels added (at stride 1), as one depth map."""
    fill_cfg = FillConfig(stride_px=1, shell_stride_px=1)
    z = depth.depth_m.copy()
    if kind == "image":
        disp, mask = fill_disparity(depth, fill_cfg, strided=False)
        fb = depth.intrinsics.fx_px * depth.baseline_m
        z[mask] = fb / disp[mask]
    else:  # the pipeline's own world points, put back into the rectified pixels they came from
        pts, _ = fill_points_in_world(
            depth, left_pose, fill_cfg, min_depth_m=cfg.min_depth_m,
            max_depth_m=cfg.max_depth_m, room_box_m=room_box,
        )  # fmt: skip
        rect = (depth.rect_from_left @ (pts.astype(np.float64) @ left_pose.R.T + left_pose.t_m).T).T
        k = depth.intrinsics
        u = np.rint(rect[:, 0] / rect[:, 2] * k.fx_px + k.cx_px).astype(int)
        v = np.rint(rect[:, 1] / rect[:, 2] * k.fy_px + k.cy_px).astype(int)
        h, w = z.shape
        ok = (
            (u >= 0)
            & (u < w)
            & (v >= 0)
            & (v < h)
            & ~depth.valid[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
        )
        z[v[ok], u[ok]] = rect[ok, 2]
    valid = np.isfinite(z) & (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m)
    z[~valid] = np.nan
    return replace(depth, depth_m=z, valid=valid)


def relative_errors(depth: DepthMap, sensor, truth_depth: np.ndarray) -> np.ndarray:
    """|z - z_true| / z_true of each valid depth, along its ray, where the truth is smooth."""
    points, _ = depth.points_in_left_camera()
    cam = Camera(name="left", intrinsics=sensor, pose=Pose(R=np.eye(3)))
    px, z = cam.project(points.astype(np.float64))
    h, w = truth_depth.shape
    x, y = px[:, 0], px[:, 1]
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = x - x0, y - y0
    n = np.stack(
        [truth_depth[y0, x0], truth_depth[y0, x0 + 1], truth_depth[y0 + 1, x0],
         truth_depth[y0 + 1, x0 + 1]]
    )  # fmt: skip
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    with np.errstate(invalid="ignore"):
        smooth = inside & np.isfinite(n).all(0) & (n.max(0) - n.min(0) < 0.01 * n.min(0))
    zt = n[0] * (1 - fx) * (1 - fy) + n[1] * fx * (1 - fy) + n[2] * (1 - fx) * fy + n[3] * fx * fy
    return np.abs(z[smooth] - zt[smooth]) / zt[smooth]


def score(depth: DepthMap, sensor, truth_depth, inside, textured, blank) -> dict[str, float]:
    rel = relative_errors(depth, sensor, truth_depth)
    w = depth.valid.shape[1]
    centre = slice(w // 2 - EDGE_COLUMNS // 2, w // 2 + EDGE_COLUMNS // 2)
    right = slice(w - EDGE_COLUMNS, w)

    def dens(cols, where=inside):
        return float(depth.valid[:, cols][where[:, cols]].mean())

    return {
        "density": float(depth.valid[inside].mean()),
        "textured": float(depth.valid[inside & textured].mean()),
        "blank": float(depth.valid[inside & blank].mean()),
        ">1%": float(np.mean(rel > 0.01)),
        ">3%": float(np.mean(rel > 0.03)),
        ">5%": float(np.mean(rel > 0.05)),
        "right": dens(right),
        "centre": dens(centre),
        "right tex": dens(right, inside & textured),
        "centre tex": dens(centre, inside & textured),
    }


def material_masks(world, unit, t_s: float, rect, object_index: np.ndarray):
    """(textured, blank) masks in the rectified left image, from the sim's object labels."""
    names = [o.name.split(":")[-1] for o in world.scene_at(t_s).objects] + ["?"]
    mx, my = rect.map_left
    labels = cv2.remap(object_index.astype(np.float32), mx, my, cv2.INTER_NEAREST)
    if rect.match_size != rect.full_size:
        labels = cv2.resize(labels, rect.match_size, interpolation=cv2.INTER_NEAREST)
    kinds = np.array(names)[np.clip(labels.astype(int), -1, len(names) - 1)]
    return np.isin(kinds, TEXTURED), np.isin(kinds, BLANK)


def as_recorded(rgb: np.ndarray, quality: int) -> np.ndarray:
    """The image after the agents' JPEG encoding (RGB in, RGB out); ``quality`` 0: raw."""
    if quality <= 0:
        return rgb
    ok, buf = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1])


def table(results, names, by_camera: bool) -> str:
    key = ("phase", "camera", "matcher") if by_camera else ("phase", "matcher")
    lines = ["| " + " | ".join(key + COLUMNS) + " |", "|---" * (len(key) + len(COLUMNS)) + "|"]
    groups = defaultdict(list)
    for phase, serial, name, s in results:
        if name in names:
            groups[(phase, f"SN{serial}", name) if by_camera else (phase, name)].append(s)
    for k, ss in groups.items():
        cells = [f"{100 * statistics.mean(s[c] for s in ss):.1f}" for c in COLUMNS]
        lines.append("| " + " | ".join(list(k) + cells) + " |")
    return "\n".join(lines)


def sim_results(
    selected: dict[str, Row],
    *,
    seed: int = 11,
    t_s: float = 1.0,
    phases: Sequence[str] = ("empty", "setup", "intraoperative", "turnover"),
    resolution: str = "SVGA",
    jpeg_quality: int = 90,
) -> list[tuple[str, int, str, dict[str, float]]]:
    """(phase, serial, row name, scores) of every selected row on every camera of each phase;
    ``Row.matcher`` (a factory) replaces our matcher where it is set."""
    from sim import World
    from sim.eval_set import room_bounds

    results = []
    for phase in phases:
        world = World.from_seed(seed, phase=phase)
        b = room_bounds(world)
        room_box = (np.array(b[:3]), np.array(b[3:]))
        for unit in world.rig:
            left, right = world.render_stereo(unit.index, t_s, resolution)
            left_rgb = as_recorded(left.image_rgb, jpeg_quality)
            right_rgb = as_recorded(right.image_rgb, jpeg_quality)
            st = unit.factory.stereo(resolution)
            cfg0 = StereoConfig.for_resolution(st.left.width_px)
            rect = rectifier(
                st.left, st.right, st.right_from_left, cfg0.match_scale, cfg0.rectify_alpha
            )
            inside = rect.rectify(left_rgb, right_rgb)[2]
            textured, blank = material_masks(world, unit, t_s, rect, left.object_index)
            for name, row in selected.items():
                cfg, m = row.matcher_for(cfg0)
                d = compute_depth(
                    left_rgb, right_rgb, st.left, st.right, st.right_from_left, cfg, m
                )
                if row.fill:
                    d = with_fill(d, cfg, row.fill, unit.left_pose, room_box)
                s = score(d, st.left, left.depth_m, inside, textured, blank)
                results.append((phase, unit.serial, name, s))
                print(f"  {phase} SN{unit.serial} {name}: "
                      + " ".join(f"{c} {100 * s[c]:.1f}" for c in COLUMNS), flush=True)  # fmt: skip
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--t-s", type=float, default=1.0)
    parser.add_argument("--phases", default="empty,setup,intraoperative,turnover")
    parser.add_argument("--resolution", default="SVGA")
    parser.add_argument("--jpeg-quality", type=int, default=90)
    parser.add_argument(
        "--per-camera", default=f"{OLD},{NEW},{BOTH},textbook SGBM+WLS",
        help="comma-separated rows to print per camera",
    )  # fmt: skip
    parser.add_argument("--rows", default="", help="comma-separated rows to run (all)")
    args = parser.parse_args()

    base = StereoConfig()
    selected = rows(base)
    if args.rows:
        selected = {k: v for k, v in selected.items() if k in args.rows.split(",")}
    results = sim_results(
        selected,
        seed=args.seed,
        t_s=args.t_s,
        phases=args.phases.split(","),
        resolution=args.resolution,
        jpeg_quality=args.jpeg_quality,
    )
    print("\nMean over the cameras (%):\n")
    print(table(results, set(selected), by_camera=False))
    print("\nPer camera (%):\n")
    print(table(results, set(args.per_camera.split(",")), by_camera=True))


if __name__ == "__main__":
    main()
