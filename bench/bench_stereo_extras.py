"""The answers a denser stereo config adds to the default's, on the real pairs and on the sim, side
by side in the same terms: their disparity, their error in px and as a share of the disparity
(the share of depth), and how the image's texture and the photometric check's ZNCC split the
right from the wrong ones (EVALUATION.md, "Why the densest config loses egocentric PSNR").

    nice -n 10 .venv/bin/python bench/bench_stereo_extras.py \\
        [--config bench/configs/stereo_densest.toml] [--no-sim]

The real pairs are ``bench/stereo_pairs.py``'s at match scale 1 (as ``bench_stereo_real.py``);
the sim's are the instants of ``bench/bench_stereo_added.py`` (seed 3, t = 2 s, set 0 of setup,
intraoperative and turnover, SVGA through JPEG 90), where a depth's error is judged at the
nearest true-depth pixel and its px error is that share times its disparity. *Wrong* is more
than 2 px off on the real pairs and more than 3 % of the depth off on the sim; the *3 % of d*
column applies the sim's test to both.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_stereo import CachedSgbm, as_recorded
from bench.bench_stereo_added import OFF, errors_at, sensor_kinds
from bench.bench_stereo_real import identity_calibration
from bench.stereo_pairs import PAIR_NAMES, PairMissingError, load_pair
from reconstructor.config import ReconstructConfig
from reconstructor.depth.sgbm import _grey, _highpass, zncc_at_disparity
from reconstructor.depth.stereo import compute_depth
from reconstructor.depth.stereo_config import StereoConfig

TEXTURE_SD = (1.0, 2.0)  # grey levels: the high-passed 7 x 7 window's SD splitting the table
ZNCC_SPLIT = 0.5


class Kept(CachedSgbm):
    """The matcher, keeping its inputs and SGBM's raw maps for the features."""

    def match(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        self.left_rgb, self.right_rgb = left_rgb, right_rgb
        self.raw = self.raw_disparities(
            left_rgb, right_rgb, min_disparity_px=min_disparity_px,
            max_disparity_px=max_disparity_px,
        )  # fmt: skip
        return super().match(
            left_rgb, right_rgb, min_disparity_px=min_disparity_px,
            max_disparity_px=max_disparity_px,
        )  # fmt: skip


def features(m: Kept) -> tuple[np.ndarray, np.ndarray]:
    """(texture SD, ZNCC at the best estimate) of every pixel of the matched pair."""
    a = _highpass(_grey(m.left_rgb))
    k = (m.config.zncc_window_px, m.config.zncc_window_px)
    mean = cv2.blur(a, k)
    sd = np.sqrt(np.maximum(cv2.blur(a * a, k) - mean * mean, 0.0))
    best = np.where(np.isfinite(m.raw.left), m.raw.left, m.raw.filtered)
    zncc = zncc_at_disparity(_grey(m.left_rgb), _grey(m.right_rgb), best, k[0])
    return sd, zncc


def row(name: str, disp, err_px, wrong, sd, zncc) -> str:
    """One table row over a set of answers."""

    def share(mask: np.ndarray) -> str:
        return f"{100 * wrong[mask].mean():.1f}" if mask.any() else "-"

    rel = err_px / disp
    lo, hi = TEXTURE_SD
    return (
        f"| {name} | {len(disp)} | {np.median(disp):.1f} ({np.percentile(disp, 5):.0f}-"
        f"{np.percentile(disp, 95):.0f}) | {np.median(err_px):.2f} | "
        f"{100 * np.mean(err_px > 2):.1f} | {100 * np.mean(rel > OFF):.1f} | "
        f"{share(np.ones(len(disp), bool))} | {share(sd < lo)} | {share(sd < hi)} | "
        f"{share(sd >= hi)} | {share(zncc < ZNCC_SPLIT)} | {share(zncc >= ZNCC_SPLIT)} |"
    )


def real_rows(base: StereoConfig, denser: StereoConfig) -> list[str]:
    out = []
    for pair_name in PAIR_NAMES:
        try:
            pair = load_pair(pair_name)
        except PairMissingError as e:
            print(f"  {pair_name}: skipped ({e})")
            continue
        disp, matchers = {}, {}
        for name, c in (("default", base), ("denser", denser)):
            cfg = replace(c, match_scale=1.0)
            intr, pose = identity_calibration(pair, cfg)
            matchers[name] = Kept(cfg)
            d = compute_depth(pair.left_rgb, pair.right_rgb, intr, intr, pose, cfg, matchers[name])
            disp[name] = np.where(d.valid, d.disparity_px, np.nan)
        truth = pair.disparity_px
        sd, zncc = features(matchers["denser"])
        with np.errstate(invalid="ignore"):
            err = np.abs(disp["denser"] - truth)
            err0 = np.abs(disp["default"] - truth)
        known = np.isfinite(truth)
        added = known & np.isfinite(disp["denser"]) & ~np.isfinite(disp["default"])
        ans0 = known & np.isfinite(disp["default"])
        out.append(row(f"{pair_name}: default's answers", disp["default"][ans0], err0[ans0],
                       err0[ans0] > 2, sd[ans0], zncc[ans0]))  # fmt: skip
        out.append(row(f"{pair_name}: added", disp["denser"][added], err[added], err[added] > 2,
                       sd[added], zncc[added]))  # fmt: skip
        print(f"  {pair_name} done", flush=True)
    return out


def sim_rows(base: ReconstructConfig, denser: ReconstructConfig) -> list[str]:
    from sim import World

    cols: dict[str, list[list[np.ndarray]]] = {"default": [], "added": []}
    for phase in ("setup", "intraoperative", "turnover"):
        world = World.from_seed(3, phase=phase)
        objects = [o.name for o in world.scene_at(2.0).objects]
        for unit in world.rig:
            left, right = world.render_stereo(unit, 2.0, "SVGA")
            lrgb, rrgb = as_recorded(left.image_rgb, 90), as_recorded(right.image_rgb, 90)
            st = unit.factory.stereo("SVGA")
            kinds = sensor_kinds(objects, left.object_index)
            depth, err, matchers = {}, {}, {}
            for name, c in (("default", base), ("denser", denser)):
                stereo = c.resolved(st.left.width_px).stereo
                assert stereo is not None
                matchers[name] = Kept(stereo)
                d = compute_depth(
                    lrgb, rrgb, st.left, st.right, st.right_from_left, stereo, matchers[name]
                )
                e, _ = errors_at(d.points_in_left_camera()[0], st.left, left.depth_m, kinds)
                err[name] = np.full(d.valid.shape, np.nan)
                err[name][d.valid] = e
                depth[name] = d
            sd, zncc = features(matchers["denser"])
            d0, d1 = depth["default"], depth["denser"]
            for key, d, mask in (
                ("default", d0, d0.valid & np.isfinite(err["default"])),
                ("added", d1, d1.valid & ~d0.valid & np.isfinite(err["denser"])),
            ):
                e = err["denser" if key == "added" else "default"][mask]
                disp = d.disparity_px[mask]
                cols[key].append([disp, e * disp, e > OFF, sd[mask], zncc[mask]])
        print(f"  {phase} done", flush=True)
    return [
        row(
            f"sim: {'default answers' if k == 'default' else 'added'}",
            *(np.concatenate(c) for c in zip(*v, strict=True)),
        )
        for k, v in cols.items()
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="bench/configs/stereo_densest.toml", type=Path)
    ap.add_argument("--no-sim", action="store_true", help="the real pairs only")
    args = ap.parse_args()
    if not args.config.is_file():
        print(f"--config {args.config}: no such file", file=sys.stderr)
        return 2
    denser = ReconstructConfig.read(args.config)
    base = ReconstructConfig()
    lo, hi = TEXTURE_SD
    lines = [
        "| answers | pixels | disparity px: median (5-95 %) | median error px | > 2 px off % | "
        f"> 3 % of d off % | wrong % | wrong, SD < {lo:g} | wrong, SD < {hi:g} | wrong, SD >= "
        f"{hi:g} | wrong, ZNCC < {ZNCC_SPLIT:g} | wrong, ZNCC >= {ZNCC_SPLIT:g} |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    stereo = denser.resolved(1920).stereo  # the table's fields; the match scale is set per pair
    assert stereo is not None
    lines += real_rows(StereoConfig(), stereo)
    if not args.no_sim:
        lines += sim_rows(base, denser)
    print("\n" + "\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
