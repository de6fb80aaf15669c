"""Stereo depth against the sim's true depth: our SGBM+WLS matcher (before and after the right-edge
fix, and with its checks loosened one at a time) beside OpenCV's textbook SGBM+WLS, on the same
rectified frames, per phase and per camera.

    .venv/bin/python bench/bench_stereo.py [--seed 11] [--t-s 1.0] [--phases empty,setup,...]

For every (phase, camera, matcher): ``density`` is the share of the rectified left image (pixels
that came from inside the sensor) with a depth; ``>1 % / >3 % / >5 %`` are the shares of those
depths more than 1, 3 or 5 % off the sim's true depth along the same ray (pixels on a true depth
edge, where the four truth neighbours differ by more than 1 %, are left out of the error, as in
tests/reconstructor/test_stereo.py); ``right`` and ``centre`` are the densities of the right-most
120 columns and of the central 120. Prints Markdown tables: every camera, then the mean per phase.
EVALUATION.md ("Stereo depth against the sim's truth") records a run.
"""

from __future__ import annotations

import argparse
import math
import statistics
from collections import defaultdict
from dataclasses import replace

import cv2
import numpy as np

from protocol.camera import Camera, Pose
from reconstructor.depth.matcher import StereoMatcher
from reconstructor.depth.sgbm import SgbmWlsMatcher, _grey, lr_consistent, zncc_at_disparity
from reconstructor.depth.stereo import compute_depth
from reconstructor.depth.stereo_config import StereoConfig

EDGE_COLUMNS = 120


class TextbookSgbmWls(StereoMatcher):
    """OpenCV's textbook SGBM+WLS (the ximgproc disparity-filtering sample with the issue's
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


class LeftPadOnly(SgbmWlsMatcher):
    """The matcher as it was before issue 22's fix (commit 955510e): padding on the left only,
    and the right-view matcher's invalid code read as a disparity. Kept to measure the fix."""

    name = "sgbm-left-pad"

    def match(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        cfg = self.config
        w = cfg.block_size_px
        min_d = max(0, math.floor(min_disparity_px) - 1)
        num_d = 16 * math.ceil((math.ceil(max_disparity_px) + 1 - min_d) / 16)
        lm = cv2.StereoSGBM.create(
            minDisparity=min_d, numDisparities=num_d, blockSize=w, P1=8 * 3 * w * w,
            P2=32 * 3 * w * w, disp12MaxDiff=-1, uniquenessRatio=cfg.uniqueness_ratio,
            speckleWindowSize=cfg.speckle_window_px, speckleRange=cfg.speckle_range_px,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )  # fmt: skip
        rm = cv2.ximgproc.createRightMatcher(lm)
        pad = min_d + num_d
        lp = cv2.copyMakeBorder(left_rgb, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
        rp = cv2.copyMakeBorder(right_rgb, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
        dl, dr = lm.compute(lp, rp), rm.compute(rp, lp)
        wls = cv2.ximgproc.createDisparityWLSFilter(lm)
        wls.setLambda(cfg.wls_lambda)
        wls.setSigmaColor(cfg.wls_sigma_color)
        out = wls.filter(dl, lp, disparity_map_right=dr)[:, pad:].astype(np.float32) / 16.0
        raw_l = dl[:, pad:].astype(np.float32) / 16.0
        raw_r = -dr[:, pad:].astype(np.float32) / 16.0
        ok = lr_consistent(raw_l, raw_r, cfg.lr_max_diff_px) & (raw_l >= min_d)
        ok &= np.abs(out - raw_l) <= cfg.wls_max_change_px
        zncc = zncc_at_disparity(
            _grey(left_rgb), _grey(right_rgb), np.where(ok, raw_l, 0.0), cfg.zncc_window_px
        )
        ok &= zncc >= cfg.min_zncc
        out[~ok] = np.nan
        return out


def matchers() -> dict[str, StereoMatcher]:
    """Each row: one change from the row it names."""
    base = StereoConfig()
    return {
        "ours, before the fix (left pad)": LeftPadOnly(base),
        "ours (both sides padded)": SgbmWlsMatcher(base),
        "ours, ZNCC check off": SgbmWlsMatcher(replace(base, min_zncc=-1.0)),
        "ours, min ZNCC 0.3": SgbmWlsMatcher(replace(base, min_zncc=0.3)),
        "ours, WLS agreement 1.0 px": SgbmWlsMatcher(replace(base, wls_max_change_px=1.0)),
        "ours, min ZNCC 0.3 + WLS agreement 1.0 px": SgbmWlsMatcher(
            replace(base, min_zncc=0.3, wls_max_change_px=1.0)
        ),
        "textbook SGBM+WLS": TextbookSgbmWls(),
    }


def truth_along_rays(depth, sensor, truth_depth):
    """(relative error of each valid depth, its (v, u) pixel) where the truth is smooth."""
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


def score(depth, sensor, truth_depth, inside) -> dict[str, float]:
    rel = truth_along_rays(depth, sensor, truth_depth)
    w = depth.valid.shape[1]
    centre = slice(w // 2 - EDGE_COLUMNS // 2, w // 2 + EDGE_COLUMNS // 2)
    right = slice(w - EDGE_COLUMNS, w)

    def dens(cols):
        return float(depth.valid[:, cols][inside[:, cols]].mean())

    return {
        "density": float(depth.valid[inside].mean()),
        ">1%": float(np.mean(rel > 0.01)),
        ">3%": float(np.mean(rel > 0.03)),
        ">5%": float(np.mean(rel > 0.05)),
        "right": dens(right),
        "centre": dens(centre),
    }


COLUMNS = ("density", ">1%", ">3%", ">5%", "right", "centre")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--t-s", type=float, default=1.0)
    parser.add_argument("--phases", default="empty,setup,intraoperative,turnover,wand")
    parser.add_argument("--resolution", default="SVGA")
    args = parser.parse_args()

    from reconstructor.depth.stereo import rectifier
    from sim import World

    rows = []  # (phase, camera, matcher, scores)
    for phase in args.phases.split(","):
        world = World.from_seed(args.seed, phase=phase)
        for unit in world.rig:
            left, right = world.render_stereo(unit.index, args.t_s, args.resolution)
            st = unit.factory.stereo(args.resolution)
            cfg = StereoConfig.for_resolution(st.left.width_px)
            rect = rectifier(
                st.left, st.right, st.right_from_left, cfg.match_scale, cfg.rectify_alpha
            )
            inside = rect.rectify(left.image_rgb, right.image_rgb)[2]
            for name, m in matchers().items():
                d = compute_depth(
                    left.image_rgb, right.image_rgb, st.left, st.right, st.right_from_left, cfg, m
                )
                rows.append((phase, unit.serial, name, score(d, st.left, left.depth_m, inside)))
                print(f"  {phase} SN{unit.serial} {name}: {rows[-1][3]}", flush=True)

    head = "| phase | camera | matcher | " + " | ".join(COLUMNS) + " |"
    print("\n" + head + "\n" + "|---" * (len(COLUMNS) + 3) + "|")
    for phase, serial, name, s in rows:
        cells = " | ".join(f"{100 * s[c]:.1f}" for c in COLUMNS)
        print(f"| {phase} | SN{serial} | {name} | {cells} |")
    print("\nMean over the cameras (%):\n")
    print("| phase | matcher | " + " | ".join(COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 2) + "|")
    groups = defaultdict(list)
    for phase, _, name, s in rows:
        groups[(phase, name)].append(s)
    for (phase, name), ss in groups.items():
        cells = " | ".join(f"{100 * statistics.mean(s[c] for s in ss):.1f}" for c in COLUMNS)
        print(f"| {phase} | {name} | {cells} |")


if __name__ == "__main__":
    main()
