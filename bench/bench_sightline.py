"""Line of sight against the simulator's exact truth: over every person x every
screen x two positions (their own eye and a counterfactual offset) x 20 timestamps over a span in
which people walk, the sightline answer against rays cast through the true scene
(``sim.roles.true_visible_fraction``). Prints, per viewer and in all: how often "at least half
visible" agrees with the truth, the visible fraction's mean absolute error and its bias.

Two kinds of model:
- **true surface** (default): at each timestamp, Gaussians at the true surface points the rig's
  eight sensors see (a quarter-size true depth map each), so the geometry is exact up to the
  Gaussians' size. This is the method's own error.
- **a reconstructed case** (``--case``): the case's models at the same timestamps (the nearest
  one each), the session's world for the truth. Method plus reconstruction error.
- **a case's stored points** (``--case ... --occluders points``): each timestamp's fused stereo
  points (stored with its model, ``storage.load_points``) made into Gaussians as the true
  surfaces are (opacity 0.9, each as wide as its neighbours' spacing): what the cameras saw,
  without training's translucent spread. Method plus stereo error.

Examples::

    .venv/bin/python bench/bench_sightline.py                     # seed 3, t = 2, 5, ..., 59 s
    .venv/bin/python bench/bench_sightline.py --case /tmp/st/case60f --occluder-scale 1 0.6
    .venv/bin/python bench/bench_sightline.py --times 2:8:2 --misses   # quick, list the misses

Several ``--occluder-scale`` values run side by side on the same models (a comparison of the
method's one tuning knob, ``SightlineConfig.occluder_scale``); ``--conserve-opacity K ...`` adds
configs that shrink by K and keep each Gaussian's integrated opacity
(``SightlineConfig.conserve_opacity``). ``--csv`` writes every instant (truth, each config's
answer, the observed share and, for a miss, its cause: who stands on the line to the blocked
points, ``plan.who_blocks``, and whether a head clearance of ``NEAR_CHECK_M`` clears it, which
points at the viewer's own shoulders or a neighbour within reach).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reconstructor.raster import RasterConfig
from reconstructor.replay.path import CameraPath
from reconstructor.replay.sightline import (
    SightlineConfig,
    parse_offset,
    visible_fraction,
)
from reconstructor.splats.gaussians import GaussianInitConfig, Gaussians, init_from_points
from sim.roles import role_trajectories, site_boxes, true_visible_fraction
from sim.world import World

VISIBLE_ENOUGH = 0.5  # the binary answer: at least half visible
NEAR_CHECK_M = 0.6  # a miss's cause: does leaving out what lies this near the eye clear it?


def true_surface_gaussians(world: World, t_s: float, shrink: int = 4) -> Gaussians:
    """Gaussians at the true surface points each sensor of the rig sees at ``t_s`` (a
    ``shrink``-times smaller true depth map), coloured as seen, opacity 0.9, each as wide as
    its neighbours' spacing (``init_from_points``): exact geometry up to the Gaussians' size."""
    points, colours = [], []
    for unit in world.rig:
        for side in ("left", "right"):
            cam = unit.sensor(side, "SVGA")
            small = cam.intrinsics.shrunk(shrink)
            r = world.render(world.virtual_camera(cam.pose, small, name="truth"), t_s)
            v, u = np.nonzero(np.isfinite(r.depth_m))
            z = r.depth_m[v, u]
            xyz = np.stack([(u - small.cx_px) / small.fx_px * z,
                            (v - small.cy_px) / small.fy_px * z, z], 1)  # fmt: skip
            points.append((xyz - cam.pose.t_m) @ cam.pose.R)
            colours.append(r.image_rgb[v, u] / 255.0)
    return init_from_points(
        np.concatenate(points), np.concatenate(colours), GaussianInitConfig(opacity=0.9)
    )


@dataclass(frozen=True)
class Case:
    t_s: float
    viewer: str
    target: str
    position: str  # "actual" or the offset's text
    truth: float
    ours: tuple[float, ...]  # one per compared config
    observed: float = float("nan")  # the tool's observed share at the target (a case only)
    cause: str = ""  # a miss's (any config's): blockers by role, and the near check's answer


def compare(
    world: World, model_at, times_s: np.ndarray, configs: list[SightlineConfig],
    offset_text: str = "1m left-posterior", raster: RasterConfig | None = None,
    progress: bool = False, observed_at=None,
) -> list[Case]:  # fmt: skip
    """Every person x screen x (actual, offset) at each time: the truth and each config's answer.
    ``model_at(t_s)`` gives the Gaussians for case time ``t_s`` (= sim time here);
    ``observed_at(t_s, g, details, raster)``, if given, the observed share the tool reports."""
    raster = raster or RasterConfig(near_m=0.2)
    offset = parse_offset(offset_text)
    boxes = site_boxes(world)
    cases: list[Case] = []
    for k, t in enumerate(times_s):
        t0 = time.perf_counter()
        g = model_at(float(t))
        trajectories = role_trajectories(world, np.array([t]))
        heads = {tr.name: CameraPath(tr).pose(float(t)).centre_m for tr in trajectories}
        for trajectory in trajectories:
            pose = CameraPath(trajectory).pose(float(t))
            for box in boxes:
                for label, shift in (("actual", np.zeros(3)),
                                     (offset.text, offset.world_shift_m(pose))):  # fmt: skip
                    eye = pose.centre_m + shift
                    near = configs[0].head_clearance_m
                    truth = true_visible_fraction(world, float(t), eye, box, near_m=near)
                    answers = [visible_fraction(g, eye, box, raster, config=c) for c in configs]
                    ours = tuple(a[0] for a in answers)
                    share = (
                        observed_at(float(t), g, answers[0][1], raster)
                        if observed_at is not None
                        else float("nan")
                    )
                    cause = ""
                    if any((o >= VISIBLE_ENOUGH) != (truth >= VISIBLE_ENOUGH) for o in ours):
                        cause = _cause(g, eye, box, raster, configs[0], answers[0][1],
                                       people={k: v for k, v in heads.items()
                                               if k != trajectory.name})  # fmt: skip
                    cases.append(
                        Case(float(t), trajectory.name, box.name, label, truth, ours, share, cause)
                    )
        if progress:
            print(f"  t = {t:6.2f} s ({k + 1}/{len(times_s)}): {time.perf_counter() - t0:.1f} s",
                  file=sys.stderr, flush=True)  # fmt: skip
    return cases


def _cause(g, eye, box, raster, config, details, people) -> str:
    """Who stands on the line to the points ``config`` calls blocked (other roles' standing
    cylinders, ``plan.who_blocks``; "other" for none), and the answer with nothing within
    ``NEAR_CHECK_M`` of the eye (the viewer's own shoulders, a neighbour within reach)."""
    from protocol.formats.site import surface_points
    from reconstructor.replay.plan import who_blocks

    if "visible" not in details:
        return "turned away"
    pts = surface_points(box, np.asarray(eye, float), 12)
    shares = who_blocks(eye, pts, ~details["visible"], people)
    words = " ".join(f"{k}:{v:.2f}" for k, v in shares.items()) or "none blocked"
    near = dataclasses.replace(config, head_clearance_m=NEAR_CHECK_M)
    cleared = visible_fraction(g, eye, box, raster, config=near)[0]
    return f"{words}; clearance {NEAR_CHECK_M:g} m: {cleared:.2f}"


def config_label(c: SightlineConfig) -> str:
    return f"scale {c.occluder_scale:g}" + (" conserved" if c.conserve_opacity else "")


def write_csv(path: Path, cases: list[Case], configs: list[SightlineConfig]) -> None:
    import csv

    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "viewer", "target", "position", "truth", "observed",
                    *[config_label(c) for c in configs], "cause"])  # fmt: skip
        for c in cases:
            w.writerow([f"{c.t_s:g}", c.viewer, c.target, c.position, f"{c.truth:.3f}",
                        f"{c.observed:.3f}", *[f"{o:.3f}" for o in c.ours], c.cause])  # fmt: skip


def scores(cases: list[Case], i: int) -> tuple[float, float, float]:
    """(agreement of the binary answer, mean absolute error, mean signed error) of config i."""
    truth = np.array([c.truth for c in cases])
    ours = np.array([c.ours[i] for c in cases])
    agree = np.mean((ours >= VISIBLE_ENOUGH) == (truth >= VISIBLE_ENOUGH))
    return float(agree), float(np.mean(np.abs(ours - truth))), float(np.mean(ours - truth))


def _row(label: str, sel: list[Case], configs: list[SightlineConfig]) -> str:
    cells = []
    for i in range(len(configs)):
        a, e, b = scores(sel, i)
        cells.append(f"{'':21s}{100 * a:5.1f}% {e:5.3f} {b:+.3f}")
    return f"{label:16s} {len(sel):4d} | " + " | ".join(cells)


def table(cases: list[Case], configs: list[SightlineConfig], title: str) -> str:
    head = " | ".join(f"{config_label(c):>21s}: agree  MAE   bias" for c in configs)
    lines = [title, f"{'viewer':16s} {'n':>4s} | {head}"]
    viewers = list(dict.fromkeys(c.viewer for c in cases))
    for name in [*viewers, "all"]:
        sel = cases if name == "all" else [c for c in cases if c.viewer == name]
        lines.append(_row(name, sel, configs))
    return "\n".join(lines)


def observed_split(cases: list[Case], configs: list[SightlineConfig]) -> str:
    """Agreement where the tool vouches for its answer (observed share at or above
    ``ObservedConfig.well_observed_share``) and where it flags it as resting on inferred content."""
    from reconstructor.replay.observed import ObservedConfig

    well = ObservedConfig().well_observed_share
    lines = [f"by the tool's flag (observed share >= {well:g} at the target: vouched for)"]
    for label, sel in (
        ("vouched for", [c for c in cases if c.observed >= well]),
        ("flagged", [c for c in cases if not c.observed >= well]),
    ):
        lines.append(_row(label, sel, configs) if sel else f"{label:16s} {0:4d}")
    return "\n".join(lines)


def _times(text: str) -> np.ndarray:
    a, b, step = (float(v) for v in text.split(":"))
    return np.arange(a, b + 1e-9, step)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--phase", default="intraoperative")
    ap.add_argument("--times", default="2:59:3", help="first:last:step, case seconds")
    ap.add_argument("--offset", default="1m left-posterior", help="the counterfactual position")
    ap.add_argument("--case", type=Path, help="a reconstructed sim case folder (its models)")
    ap.add_argument("--occluder-scale", type=float, nargs="+", default=None,
                    help="compare these SightlineConfig.occluder_scale values")  # fmt: skip
    ap.add_argument("--occluders", choices=("model", "points"), default="model",
                    help="with --case: its models, or its stored stereo points")  # fmt: skip
    ap.add_argument("--points-opacity", type=float, default=0.9,
                    help="--occluders points: each point's opacity (0.9)")  # fmt: skip
    ap.add_argument("--conserve-opacity", type=float, nargs="+", default=[], metavar="K",
                    help="also these occluder_scale values with conserve_opacity")  # fmt: skip
    ap.add_argument("--csv", type=Path, help="write every instant here")
    ap.add_argument("--no-observed", action="store_true",
                    help="with --case: skip the observed share (a render per instant)")  # fmt: skip
    ap.add_argument("--misses", action="store_true", help="list the disagreements")
    args = ap.parse_args(argv)
    base = SightlineConfig()
    scales = args.occluder_scale or [base.occluder_scale]
    configs = [dataclasses.replace(base, occluder_scale=s) for s in scales] + [
        dataclasses.replace(base, occluder_scale=k, conserve_opacity=True)
        for k in args.conserve_opacity
    ]
    times = _times(args.times)
    raster = RasterConfig(near_m=0.2)
    if args.case is None:
        world = World.from_seed(args.seed, phase=args.phase)
        model_at = lambda t: true_surface_gaussians(world, t)  # noqa: E731
        title = f"true-surface models, seed {args.seed} {args.phase}"
    observed_at = None
    if args.case is not None:
        world, model_at, raster, times, observed_at = _case_source(
            args.case, times, args.occluders, args.points_opacity
        )
        title = f"reconstructed case {args.case} ({args.occluders})"
        if args.no_observed:
            observed_at = None
    t0 = time.perf_counter()
    cases = compare(world, model_at, times, configs, args.offset, raster, progress=True,
                    observed_at=observed_at)  # fmt: skip
    n_view = len({c.viewer for c in cases})
    print(f"{title}: {n_view} viewers x {len({c.target for c in cases})} screens x 2 positions "
          f"x {len(times)} timestamps ({times[0]:g}-{times[-1]:g} s) = {len(cases)} instants, "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    print(table(cases, configs, ""))
    if observed_at is not None:
        print(observed_split(cases, configs))
    if args.csv is not None:
        write_csv(args.csv, cases, configs)
    if args.misses:
        for c in cases:
            if any((o >= VISIBLE_ENOUGH) != (c.truth >= VISIBLE_ENOUGH) for o in c.ours):
                ours = " ".join(f"{o:.2f}" for o in c.ours)
                print(f"  miss t={c.t_s:6.2f} {c.viewer:15s} {c.target:18s} {c.position:18s} "
                      f"truth {c.truth:.2f} ours {ours}  {c.cause}")  # fmt: skip
    return 0


def _case_source(
    folder: Path, times: np.ndarray, occluders: str = "model", points_opacity: float = 0.9
):
    """The case's world (seed, phase and contact from its session, which must start at the sim
    epoch as eval-set sessions do), a loader of its models by time, the raster its sightline
    uses, the case times nearest ``times``, and the observed share the tool reports."""
    from protocol.session import SessionReader
    from reconstructor.data.views import EYE_NEAR_M
    from reconstructor.replay.models import CaseModels
    from reconstructor.replay.observed_case import CaseObserved
    from reconstructor.replay.run import case_raster
    from sim.timing import SIM_EPOCH_UNIX_NS

    models = CaseModels(folder)
    with SessionReader(Path(models.index.session)) as reader:
        meta, start = reader.info.case_metadata, reader.info.started_unix_ns
    if start != SIM_EPOCH_UNIX_NS:
        raise SystemExit(f"{folder}: its session does not start at the sim epoch (eval-set only)")
    contact = meta.get("contact") == "1"
    world = World.from_seed(int(meta["seed"]), phase=meta["phase"], contact=contact)
    by_t = {models.entry_at(float(t)).t_s: models.entry_at(float(t)) for t in times}
    chosen = np.array(sorted(by_t))
    raster = case_raster(folder, EYE_NEAR_M)
    observed = CaseObserved(folder, case_raster(folder))

    def observed_at(t, g, details, raster_):
        return observed.target_share(by_t[t], g, details, raster_)

    if occluders == "points":
        from reconstructor.case.storage import load_points

        def points_at(t):
            pts = load_points(folder, by_t[t])
            if pts is None:
                raise SystemExit(f"{folder}: {by_t[t].name} stores no points (an older case)")
            grey = np.full_like(pts, 0.5)
            return init_from_points(pts, grey, GaussianInitConfig(opacity=points_opacity))

        return world, points_at, raster, chosen, observed_at
    return world, lambda t: models.load(by_t[t]), raster, chosen, observed_at


if __name__ == "__main__":
    raise SystemExit(main())
