"""Stereo depth on real rectified pairs with ground truth, beside the sim's rows: our default
matcher as the pipeline calls it, every installed plug-in matcher, the variants tried on the way
to a denser default, and OpenCV's textbook SGBM+WLS.

    nice -n 10 .venv/bin/python bench/bench_stereo_real.py [--pairs motorcycle,aloe,aloe-half] \\
        [--rows NAME,...] [--sim-phases intraoperative] [--weights NAME=PATH] \\
        [--scale full|rig|both]

The pairs (``bench/stereo_pairs.py``): Middlebury 2014 Motorcycle from scikit-image's wheel (the
``bench`` extra) and Middlebury 2006 Aloe from Debian's ``opencv-doc`` (``make system-deps``), at
full and at half size. Every matcher runs through ``compute_depth`` on the pair as it is (an
undistorted, already rectified calibration whose rectification is the identity; match scale 1),
with the depth range set so that the search covers the true disparities (1.25 x the largest).

Per pair and matcher, over the pixels with a true disparity: ``density``, the share with an
answer; ``bad-2`` / ``bad-1``, the share that is a hole or more than 2 / 1 px off (holes count
as errors, as in Middlebury's all-pixel scores); ``bad-2 ans``, more than 2 px off among the
answers; ``bad-3%d`` / ``3%d ans``, the same in depth terms: a hole or more than 3 % of the
true disparity off (3 % of depth), with holes and among the answers; ``EPE``, the mean absolute
error in px among the answers; ``time``, seconds for the whole ``compute_depth`` (2 shared
cores: a rough figure). The sim rows are bench_stereo.py's
(the mean over the four cameras of ``--sim-phases``; ``--sim-phases ''`` skips them), with each
matcher's seconds per SVGA pair and their ratio to the default's in the same run.

``--scale rig`` judges each pair downscaled to the rig's disparities instead (``both``: too)
(``stereo_pairs.at_rig_scale``: area-averaged images, the truth at each new pixel's centre times
the factor, invalid kept invalid; median true disparity 16 px, as the rig's answers on its
960 px wide images): the matcher's checks are in pixels, so a pair at 30-60 px judges them at
2-4 times the rig's depth resolution, and 2 px there is 3-7 % of depth, 12 % on the rig.
EVALUATION.md ("Stereo depth on real images") records a run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

_ROOT = Path(__file__).resolve().parents[1]
if str(_ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(_ROOT))

from bench import stereo_fill_rules as rules  # noqa: E402
from bench.bench_stereo import Row, TextbookSgbmWls, sim_results  # noqa: E402  (after the path)
from bench.stereo_pairs import (  # noqa: E402
    PAIR_NAMES,
    PairMissingError,
    RealPair,
    at_rig_scale,
    load_pair,
)
from protocol.camera import Intrinsics, Pose  # noqa: E402
from reconstructor.depth.matcher import StereoMatcher  # noqa: E402
from reconstructor.depth.matchers import available_matchers, load_matcher  # noqa: E402
from reconstructor.depth.sgbm import RawDisparities, SgbmWlsMatcher  # noqa: E402
from reconstructor.depth.stereo import compute_depth, rectifier  # noqa: E402
from reconstructor.depth.stereo_config import StereoConfig  # noqa: E402
from reconstructor.errors import MatcherNotFoundError, MatcherWeightsError  # noqa: E402

REAL_COLUMNS = ("density", "bad-2", "bad-1", "bad-2 ans", "bad-3%d", "3%d ans", "EPE px", "time s")
DEPTH_OFF = 0.03  # "bad-3%d": more than this share of the true disparity (= of depth) off
SIM_COLUMNS = ("density", "textured", "blank", ">1%", ">3%", ">5%")
SIM_TIME = "match s"  # seconds of the matcher's ``match`` per SVGA pair
SEARCH_MARGIN = 1.25  # the search reaches this far past the largest true disparity
DEFAULT = "ours (default)"
TEXTBOOK = "textbook SGBM+WLS"


@dataclass(frozen=True)
class Variant:
    """A matcher under test: its config (None: the textbook) and how it is built from it."""

    config: StereoConfig | None
    build: Callable[[StereoConfig], StereoMatcher] = SgbmWlsMatcher


class GuidedAgreement(SgbmWlsMatcher):
    """Ours, plus the pixels where the WLS map agrees (within 0.5 px) with the kept disparities
    spread along the image's colour edges (``fill.py``'s normalised smoothing, lambda 200,
    sigma 3): two estimates that agree, tried as a confidence for the pixels the checks drop."""

    def keep(self, left_rgb: np.ndarray, right_rgb: np.ndarray, raw: RawDisparities) -> np.ndarray:
        ok = super().keep(left_rgb, right_rgb, raw)
        weight = ok.astype(np.float32)

        def smooth(x: np.ndarray) -> np.ndarray:
            return cv2.ximgproc.fastGlobalSmootherFilter(left_rgb, x, 200.0, 3.0)

        num = smooth(np.where(ok, raw.filtered, 0.0).astype(np.float32))
        den = smooth(weight)
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = num / den
            agree = (den > 0.05) & (np.abs(raw.filtered - spread) <= 0.5)
        return ok | agree


WARP_BEST = "ZNCC window: failed pixels warped by their best estimate"
SGBM_OWN = "SGBM's own where WLS differs by 0.5-1.5 px"
SGBM_OWN_ON_BEST = "window warped by the best + " + SGBM_OWN
GUIDED = "+ WLS agreeing with the image-guided spread of kept pixels"
LEFT_BORDER = SGBM_OWN_ON_BEST + " + left border's band filled"
SMOOTH_SGBM = SGBM_OWN_ON_BEST + " + SGBM's own where smooth and WLS differs by 1.5-2.5 px"
SMOOTH_SGBM_BORDER = SMOOTH_SGBM + " + left border's band filled"
DENSEST = "densest"


def variants() -> dict[str, Variant]:
    """The default, then each change tried on the way to a denser matcher (one at a time,
    EVALUATION.md), then the textbook."""
    base = StereoConfig()
    best = replace(base, zncc_warp_failed_by_best=True)
    own = replace(best, keep_sgbm_within_px=1.5)
    return {
        DEFAULT: Variant(base),
        WARP_BEST: Variant(best),
        SGBM_OWN: Variant(replace(base, keep_sgbm_within_px=1.5)),
        SGBM_OWN_ON_BEST: Variant(own),
        # each further change on top of the window warped by the best estimates
        "ZNCC check off": Variant(replace(best, min_zncc=-1.0)),
        "WLS agreement 1.0 px": Variant(replace(best, wls_max_change_px=1.0)),
        "left-right 2 px": Variant(replace(best, lr_max_diff_px=2.0)),
        "SGBM's own where WLS differs by 0.5-1.0 px": Variant(
            replace(best, keep_sgbm_within_px=1.0)
        ),
        GUIDED: Variant(best, GuidedAgreement),
        "WLS agreement 1.0 px " + GUIDED: Variant(
            replace(best, wls_max_change_px=1.0), GuidedAgreement
        ),
        # a further change on top of SGBM_OWN_ON_BEST
        SGBM_OWN_ON_BEST + ", block 3 px": Variant(replace(own, block_size_px=3)),
        LEFT_BORDER: Variant(replace(own, fill_left_border=True)),
        SMOOTH_SGBM: Variant(replace(own, keep_smooth_sgbm_within_px=2.5)),
        SMOOTH_SGBM_BORDER: Variant(
            replace(own, keep_smooth_sgbm_within_px=2.5, fill_left_border=True)
        ),
        # densest + one rule on the answers its options add (bench/stereo_fill_rules.py)
        DENSEST + " + SGBM's own only within 3 % of d": Variant(
            rules.densest(), lambda c: rules.RelativeAgreement(c, rel=0.03)
        ),
        DENSEST + " + extras only where textured (std 2)": Variant(
            rules.densest(), lambda c: rules.TextureGate(c, min_std=2.0)
        ),
        DENSEST + " + extras only where SGBM is smooth": Variant(
            rules.densest(), rules.SmoothGuard
        ),
        TEXTBOOK: Variant(None),
    }


# short names for ``--rows``: the default and the two configs of bench/configs/, and the textbook
ROW_ALIASES = {
    "default": DEFAULT,
    "dense": SGBM_OWN_ON_BEST,  # bench/configs/stereo_dense.toml
    "densest": SMOOTH_SGBM_BORDER,  # bench/configs/stereo_densest.toml
    "textbook": TEXTBOOK,
}


def identity_calibration(pair: RealPair, config: StereoConfig) -> tuple[Intrinsics, Pose]:
    """An undistorted, already rectified calibration of ``pair`` whose depth range searches
    disparities up to ``SEARCH_MARGIN`` x the largest true one (``d = f * B / z``)."""
    h, w = pair.disparity_px.shape
    f = float(w)
    intr = Intrinsics(
        width_px=w, height_px=h, fx_px=f, fy_px=f, cx_px=(w - 1) / 2, cy_px=(h - 1) / 2
    )
    d_max = SEARCH_MARGIN * float(np.nanmax(pair.disparity_px))
    baseline_m = d_max * config.min_depth_m / f
    return intr, Pose(R=np.eye(3), t_m=np.array([-baseline_m, 0.0, 0.0]))


def check_identity(intr: Intrinsics, pose: Pose, config: StereoConfig) -> None:
    """Refuse to score if rectifying the identity calibration moves a pixel (it must not)."""
    rect = rectifier(intr, intr, pose, config.match_scale, config.rectify_alpha)
    mx, my = rect.map_left
    xs, ys = np.meshgrid(np.arange(intr.width_px), np.arange(intr.height_px))
    moved = max(float(np.abs(mx - xs).max()), float(np.abs(my - ys).max()))
    if moved > 0.01:
        raise SystemExit(
            f"the identity rectification moves pixels by {moved:.3f} px: fix the bench"
        )


def real_scores(disp: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The columns of ``REAL_COLUMNS`` but time, as fractions (EPE in px)."""
    known = np.isfinite(truth)
    with np.errstate(invalid="ignore"):
        answered = known & np.isfinite(disp) & (disp > 0)
        err = np.abs(disp - truth)
        deep = err > DEPTH_OFF * truth  # NaN (no answer, no truth) compares False
    n, a = int(known.sum()), int(answered.sum())
    return {
        "density": a / n,
        "bad-2": 1.0 - int((answered & (err <= 2)).sum()) / n,
        "bad-1": 1.0 - int((answered & (err <= 1)).sum()) / n,
        "bad-2 ans": int((answered & (err > 2)).sum()) / max(a, 1),
        "bad-3%d": 1.0 - int((answered & ~deep).sum()) / n,
        "3%d ans": int((answered & deep).sum()) / max(a, 1),
        "EPE px": float(err[answered].mean()) if a else float("nan"),
    }


def run_pair(pair: RealPair, name: str, variant: Variant) -> dict[str, float]:
    """One matcher on one pair through ``compute_depth``: its scores and time."""
    cfg = replace(variant.config or StereoConfig(), match_scale=1.0)
    intr, pose = identity_calibration(pair, cfg)
    check_identity(intr, pose, cfg)
    m = TextbookSgbmWls() if variant.config is None else variant.build(cfg)
    t0 = time.perf_counter()
    d = compute_depth(pair.left_rgb, pair.right_rgb, intr, intr, pose, cfg, m)
    seconds = time.perf_counter() - t0
    disp = np.where(d.valid, d.disparity_px, np.nan)
    return {**real_scores(disp, pair.disparity_px), "time s": seconds}


def _built(matcher: StereoMatcher) -> Callable[[StereoConfig], StereoMatcher]:
    """A plug-in, already built, as a ``Variant.build`` (plug-ins take no StereoConfig)."""

    def build(_config: StereoConfig) -> StereoMatcher:
        return matcher

    return build


def plugin_variants(weights: dict[str, Path]) -> dict[str, Variant]:
    """Every installed plug-in matcher that can be built (weights from ``--weights``)."""
    out = {}
    for name in available_matchers():
        if name == "sgbm":
            continue
        try:
            matcher = load_matcher(name, weights.get(name))
        except (MatcherWeightsError, MatcherNotFoundError) as e:
            print(f"  plug-in {name}: skipped ({e})")
            continue
        out[f"plug-in {name}"] = Variant(StereoConfig(), _built(matcher))
    return out


def real_table(results: list[tuple[str, str, dict[str, float]]]) -> str:
    lines = [
        "| pair | matcher | " + " | ".join(REAL_COLUMNS) + " |",
        "|---|---|" + "---|" * len(REAL_COLUMNS),
    ]
    by_matcher = defaultdict(list)
    for pair, name, s in results:
        by_matcher[name].append(s)
        lines.append(f"| {pair} | {name} | " + _cells(s) + " |")
    for name, ss in by_matcher.items():
        mean = {c: statistics.mean(s[c] for s in ss) for c in REAL_COLUMNS}
        lines.append(f"| mean | {name} | " + _cells(mean) + " |")
    return "\n".join(lines)


def _cells(s: dict[str, float]) -> str:
    return " | ".join(
        f"{s[c]:.2f}" if c in ("EPE px", "time s") else f"{100 * s[c]:.1f}" for c in REAL_COLUMNS
    )


class TimedMatcher(StereoMatcher):
    """A matcher that adds the seconds of each ``match`` to ``seconds[row]``."""

    def __init__(self, inner: StereoMatcher, row: str, seconds: dict[str, list[float]]) -> None:
        self.inner, self.row, self.seconds = inner, row, seconds
        self.name = inner.name  # type: ignore[misc]  (the seam's ClassVar, per instance here)

    def match(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        t0 = time.perf_counter()
        out = self.inner.match(
            left_rgb,
            right_rgb,
            min_disparity_px=min_disparity_px,
            max_disparity_px=max_disparity_px,
        )
        self.seconds[self.row].append(time.perf_counter() - t0)
        return out


def sim_rows(selected: dict[str, Variant], seconds: dict[str, list[float]]) -> dict[str, Row]:
    """bench_stereo's rows for ``selected``, each matcher timed into ``seconds`` (the textbook
    as well: a row with a config whose matcher is the textbook's)."""

    def timed(name: str, v: Variant) -> Callable[[StereoConfig], StereoMatcher]:
        def build(cfg: StereoConfig) -> StereoMatcher:
            inner = TextbookSgbmWls() if v.config is None else v.build(cfg)
            return TimedMatcher(inner, name, seconds)

        return build

    return {k: Row(v.config or StereoConfig(), matcher=timed(k, v)) for k, v in selected.items()}


def sim_table(results, seconds: dict[str, list[float]], reference: str = DEFAULT) -> str:
    """Mean over the cameras per phase and row; the last columns: the matcher's seconds per
    pair (every phase) and its ratio to ``reference``'s."""
    lines = ["| phase | matcher | " + " | ".join((*SIM_COLUMNS, SIM_TIME, "x default")) + " |"]
    lines.append("|---|---|" + "---|" * (len(SIM_COLUMNS) + 2))
    groups = defaultdict(list)
    for phase, _serial, name, s in results:
        groups[(phase, name)].append(s)
    ref = statistics.mean(seconds[reference]) if seconds.get(reference) else float("nan")
    for (phase, name), ss in groups.items():
        cells = " | ".join(f"{100 * statistics.mean(s[c] for s in ss):.1f}" for c in SIM_COLUMNS)
        t = statistics.mean(seconds[name]) if seconds.get(name) else float("nan")
        lines.append(f"| {phase} | {name} | {cells} | {t:.2f} | {t / ref:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pairs", default=",".join(PAIR_NAMES))
    parser.add_argument(
        "--rows",
        default="",
        help="comma-separated matchers to run, by name or as default, dense, densest, "
        "textbook (all)",
    )
    parser.add_argument("--sim-phases", default="intraoperative", help="'' skips the sim rows")
    parser.add_argument("--weights", action="append", default=[], help="plug-in NAME=PATH")
    parser.add_argument(
        "--scale",
        choices=("full", "rig", "both"),
        default="full",
        help="each pair as it is, downscaled to the rig's disparities (median 16 px), or both",
    )
    args = parser.parse_args()

    weights = dict(w.split("=", 1) for w in args.weights)
    selected = {**variants(), **plugin_variants({k: Path(v) for k, v in weights.items()})}
    if args.rows:
        wanted = {ROW_ALIASES.get(r, r) for r in args.rows.split(",")}
        selected = {k: v for k, v in selected.items() if k in wanted}
    unknown = [n for n in args.pairs.split(",") if n not in PAIR_NAMES]
    if unknown:
        parser.error(f"no stereo pair called {unknown[0]!r}; choose from {', '.join(PAIR_NAMES)}")
    if not selected:
        parser.error(
            f"--rows {args.rows!r} names no matcher: name them as the table does, or as "
            "default, dense, densest, textbook"
        )
    results: dict[str, list[tuple[str, str, dict[str, float]]]] = {"full": [], "rig": []}
    scales = ("full", "rig") if args.scale == "both" else (args.scale,)
    for pair_name in args.pairs.split(","):
        try:
            full = load_pair(pair_name)
        except PairMissingError as e:
            print(f"  {pair_name}: skipped ({e})")
            continue
        for scale in scales:
            pair = full if scale == "full" else at_rig_scale(full)
            for name, variant in selected.items():
                s = run_pair(pair, name, variant)
                results[scale].append((pair.name, name, s))
                print(f"  {pair.name} {name}: {_cells(s)}", flush=True)
    if results["full"]:
        print("\nReal pairs (%, EPE in px, time in s):\n")
        print(real_table(results["full"]))
    if results["rig"]:
        print("\nReal pairs at the rig's disparities (median 16 px; %, EPE in px, time in s):\n")
        print(real_table(results["rig"]))
    if args.sim_phases:
        seconds: dict[str, list[float]] = defaultdict(list)
        sim = sim_results(sim_rows(selected, seconds), phases=args.sim_phases.split(","))
        print("\nThe sim, mean over the four cameras (%; the matcher's seconds per pair):\n")
        print(sim_table(sim, seconds))


if __name__ == "__main__":
    main()
