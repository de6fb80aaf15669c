"""What estimated roles cost a reviewer: the line of sight and the egocentric view of a
reconstructed sim case, with the eyes ``egosurg people`` found against the sim's true eyes.

The people file (``egosurg people``, made for the case's session) is named by the simulator's
truth the way the demo names it (``sim.demo_names.name_by_truth``: each track after the person
whose true eye is nearest it, median over its keyframes, within 0.5 m; a person takes every
such track that does not overlap one already theirs) and written as a roles file with
``egosurg people name``'s code: a role is its tracks joined, the time between them a gap. At
each case timestamp of ``--times`` (the nearest model), every person the named roles cover is
reviewed twice, once from the estimated eye and once from the true one (``World.head_poses``),
and both answers are judged against the same truth:

- **line of sight**: each screen x (their own position, ``--offset``): the sightline answer
  (``reconstructor.replay.sightline.visible_fraction``, the default ``SightlineConfig``) against
  rays cast through the true scene from the TRUE eye (``sim.roles.true_visible_fraction``):
  agreement of "at least half visible" and the visible fraction's MAE, as
  bench/bench_sightline.py scores them. The offset moves each eye in its own facing's frame.
- **egocentric PSNR**: the case's model rendered from the eye and gaze (Table 4's protocol:
  90 deg horizontal field of view, the person's own head left out within ``EYE_NEAR_M``)
  against the simulator's noise-free render from the TRUE head pose, mean over views.

A person not named, or at a time outside their tracks' keyframes or inside one of the role's
gaps (hidden from every camera, or between two of its tracks: replay and sightline show no view
there), gets no answer from the review tools; the table counts those instants apart and scores
both eyes on the same answered instants (the true eyes also over every instant, the
line-of-sight bench's own number).

Example (docs: EVALUATION.md, "People from the recording")::

    egosurg people SESSION_2HZ.h5 --every 0.5 --out people.toml
    .venv/bin/python bench/bench_people_review.py --case c3_3 --people people.toml \\
        --times 2:56:12 --roles-out roles.toml
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from bisect import bisect_left
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_sightline import VISIBLE_ENOUGH, _case_source, _times
from protocol.formats.trajectory import TIME_RESOLUTION_S, Trajectory, read_trajectory_file
from reconstructor.data.views import EYE_NEAR_M, novel_view
from reconstructor.errors import SightlineError
from reconstructor.evaluation.methods import render_splats
from reconstructor.evaluation.metrics import psnr
from reconstructor.replay.names import role_lines, write_roles
from reconstructor.replay.path import CameraPath
from reconstructor.replay.session_check import CaseInputs
from reconstructor.replay.sightline import SightlineConfig, parse_offset, visible_fraction
from sim.demo_names import MAX_NAMING_M, TruthName, median_distances_m, name_by_truth
from sim.roles import site_boxes, true_visible_fraction
from sim.world import World


@dataclass(frozen=True)
class Sight:
    t_s: float
    viewer: str
    target: str
    position: str
    truth: float  # from the true eye, through the true scene
    from_true: float  # the tool's answer from the true eye
    from_est: float  # from the estimated eye (nan: the roles give none at t_s)
    eye_err_m: float = float("nan")  # the estimated eye's distance from the true one
    in_gap: bool = False  # from_est is the spline through one of the role's gaps: no answer
    refused: bool = False  # the estimated eye lies in the target's box: from_est 0, none seen


@dataclass(frozen=True)
class Ego:
    t_s: float
    viewer: str
    psnr_true_db: float
    psnr_est_db: float
    eye_err_m: float
    gaze_err_deg: float  # between the estimated and the true optical axes
    in_gap: bool = False  # see Sight.in_gap


def name_longest(people: Path, true_eyes, max_m: float = MAX_NAMING_M) -> list[TruthName]:
    """``--naming longest``: each track to the person whose true eye is nearest it (median over
    its keyframes, within ``max_m``); each person then takes, of their tracks, the set that
    does not overlap with the most keyframes (a reviewer naming the tracks that follow someone
    longest), where the demo's rule takes the nearest first."""
    mine: dict[str, list[tuple[Trajectory, float]]] = {}
    for t in read_trajectory_file(people).trajectories:
        d = median_distances_m(t, true_eyes)
        role = min(d, key=lambda r: d[r]) if d else None
        if role is not None and d[role] <= max_m:
            mine.setdefault(role, []).append((t, d[role]))
    named: list[TruthName] = []
    for role, cands in mine.items():
        cands.sort(key=lambda c: c[0].span_s[1])
        ends = [c[0].span_s[1] for c in cands]
        best: list[tuple[int, list]] = [(0, [])]  # over the first k candidates: (keyframes, picks)
        for k, (t, dist) in enumerate(cands):
            j = bisect_left(ends, t.span_s[0], hi=k)  # those ending before this one starts
            take = (best[j][0] + len(t.keyframes), [*best[j][1], (t, dist)])
            best.append(max(best[k], take, key=lambda b: b[0]))
        named += [TruthName(t.name, role, dist) for t, dist in best[-1][1]]
    return sorted(named, key=lambda n: n.median_m)


def name_people(people: Path, world: World, roles_out: Path, naming: str = "nearest"):
    """The people file's tracks named by the sim's true eyes (case time = sim time: eval-set
    sessions start at the sim epoch), written to ``roles_out`` as ``egosurg people name`` does."""

    def true_eyes(t_s: float) -> dict[str, np.ndarray]:
        return {n: p.centre_m for n, p in world.head_poses(t_s).items()}

    named = name_longest(people, true_eyes) if naming == "longest" else (
        name_by_truth(people, true_eyes)
    )  # fmt: skip
    write_roles(roles_out, read_trajectory_file(people), {n.track: n.role for n in named})
    return named


def estimated_pose(roles: dict[str, CameraPath], name: str, t_s: float, gaps: bool = False):
    """The role's pose where the review tools give one: inside its keyframes, not in a gap
    (``gaps``: in a gap too, the spline's pose there, which the tools do not show)."""
    path = roles.get(name)
    if path is None or (path.gap_at(t_s) is not None and not gaps):
        return None
    t0, t1 = path.span_s
    tol = TIME_RESOLUTION_S  # a keyframe's time, read back from the file, is this close
    return path.pose(t_s) if t0 - tol <= t_s <= t1 + tol else None


def review(world, model_at, times_s, roles: list[Trajectory], raster, offset_text: str,
           size_px: tuple[int, int]) -> tuple[list[Sight], list[Ego]]:  # fmt: skip
    """Every person x screen x position at each time: the truth, and the answer from each eye;
    every covered person's egocentric view from each eye against the true pose's render."""
    config = SightlineConfig()
    offset = parse_offset(offset_text)
    boxes = site_boxes(world)
    paths = {r.name: CameraPath(r) for r in roles}
    sights: list[Sight] = []
    egos: list[Ego] = []
    for k, t in enumerate(times_s):
        t0 = time.perf_counter()
        t = float(t)
        g = model_at(t)
        for name, pose in world.head_poses(t).items():
            est = estimated_pose(paths, name, t, gaps=True)
            gap = est is not None and estimated_pose(paths, name, t) is None
            for box in boxes:
                for label, shift, est_shift in (
                    ("actual", np.zeros(3), np.zeros(3)),
                    (offset.text, offset.world_shift_m(pose),
                     None if est is None else offset.world_shift_m(est)),
                ):  # fmt: skip
                    eye = pose.centre_m + shift
                    truth = true_visible_fraction(
                        world, t, eye, box, near_m=config.head_clearance_m
                    )
                    ours = visible_fraction(g, eye, box, raster, config=config)[0]
                    theirs, err, refused = float("nan"), float("nan"), False
                    if est is not None:
                        err = float(np.linalg.norm(est.centre_m - pose.centre_m))
                        est_eye = est.centre_m + est_shift
                        try:
                            theirs = visible_fraction(g, est_eye, box, raster, config=config)[0]
                        except SightlineError:  # the tool refuses: the reviewer sees none of it
                            theirs, refused = 0.0, True
                    sights.append(
                        Sight(t, name, box.name, label, truth, ours, theirs, err, gap, refused)
                    )
            if est is not None:
                ego = _ego(world, g, raster, t, name, pose, est, size_px)
                egos.append(dataclasses.replace(ego, in_gap=gap))
        print(f"  t = {t:6.2f} s ({k + 1}/{len(times_s)}): {time.perf_counter() - t0:.1f} s",
              file=sys.stderr, flush=True)  # fmt: skip
    return sights, egos


def _ego(world, g, raster, t, name, pose, est, size_px) -> Ego:
    ref_cam = world.virtual_camera(pose, size_px=size_px, name=name)
    reference = world.render(ref_cam, t).image_rgb
    scores = []
    for p in (pose, est):
        cam = world.virtual_camera(p, size_px=size_px, name=name)
        img = render_splats(g, raster, novel_view(cam), near_m=EYE_NEAR_M)
        scores.append(psnr(img, reference))
    err = float(np.linalg.norm(est.centre_m - pose.centre_m))
    cos = float(np.clip(pose.R[2] @ est.R[2], -1.0, 1.0))  # rows 2: the optical axes (world)
    return Ego(t, name, scores[0], scores[1], err, float(np.degrees(np.arccos(cos))))


def los_scores(truth: np.ndarray, ours: np.ndarray) -> tuple[float, float]:
    """(agreement of "at least half visible" in %, mean absolute error of the fraction)."""
    agree = np.mean((ours >= VISIBLE_ENOUGH) == (truth >= VISIBLE_ENOUGH))
    return 100 * float(agree), float(np.mean(np.abs(ours - truth)))


NEAR_EYE_M = 0.25  # a split of the tables: the named track on its person, within this
NEAR_GAZE_DEG = 20.0  # and facing within this (the yaw goal)


def los_table(sights: list[Sight], offset_text: str) -> str:
    lines = [
        "line of sight against the truth (agreement %, MAE); both eyes on the instants the "
        "estimated roles answer",
        f"{'viewer':24s} {'all':>4s} {'true eye':>15s} | {'n':>4s} {'true eye':>15s} "
        f"{'estimated eye':>15s} {'diff pts':>8s}",
    ]
    groups = [(v, lambda s, v=v: s.viewer == v) for v in dict.fromkeys(s.viewer for s in sights)]
    groups += [
        ("all", lambda s: True),
        ("all, own position", lambda s: s.position == "actual"),
        (f"all, {offset_text}", lambda s: s.position == offset_text),
        (f"all, eye within {NEAR_EYE_M:g} m",
         lambda s: s.eye_err_m <= NEAR_EYE_M and not s.in_gap),
        ("  own position",
         lambda s: s.eye_err_m <= NEAR_EYE_M and s.position == "actual" and not s.in_gap),
        ("in the roles' gaps", lambda s: s.in_gap),  # the spline's eye there: the tools show none
    ]  # fmt: skip
    for name, keep in groups:
        sel = [s for s in sights if keep(s)]
        truth = np.array([s.truth for s in sel])
        ours = np.array([s.from_true for s in sel])
        est = np.array([s.from_est for s in sel])
        a_all, e_all = los_scores(truth, ours)
        gap_row = name == "in the roles' gaps"
        ok = np.isfinite(est) & np.array([s.in_gap == gap_row for s in sel], bool)
        head = f"{name:24s} {len(sel):4d} {a_all:6.1f}% {e_all:6.3f} | {int(ok.sum()):4d}"
        if not ok.any():
            lines.append(f"{head} {'(no answer)':>15s}")
            continue
        a_t, e_t = los_scores(truth[ok], ours[ok])
        a_e, e_e = los_scores(truth[ok], est[ok])
        lines.append(f"{head} {a_t:6.1f}% {e_t:6.3f} {a_e:6.1f}% {e_e:6.3f} {a_e - a_t:+8.1f}")
    return "\n".join(lines)


def ego_table(egos: list[Ego]) -> str:
    lines = [
        "egocentric PSNR against the true pose's render (dB, mean over views; errors: median)",
        f"{'viewer':24s} {'views':>5s} {'eye err m':>9s} {'gaze deg':>8s} {'true pose':>9s} "
        f"{'estimated':>9s} {'diff dB':>8s}",
    ]
    near = f"eye within {NEAR_EYE_M:g} m"
    groups = [(v, lambda e, v=v: e.viewer == v) for v in dict.fromkeys(e.viewer for e in egos)]
    groups += [
        ("all", lambda e: True),
        (near, lambda e: e.eye_err_m <= NEAR_EYE_M),
        (f"  gaze within {NEAR_GAZE_DEG:g} deg",
         lambda e: e.eye_err_m <= NEAR_EYE_M and e.gaze_err_deg <= NEAR_GAZE_DEG),
    ]  # fmt: skip
    groups = [(n, lambda e, k=k: k(e) and not e.in_gap) for n, k in groups]
    groups.append(("in the roles' gaps", lambda e: e.in_gap))  # the tools show no view there
    for name, keep in groups:
        sel = [e for e in egos if keep(e)]
        if not sel:
            lines.append(f"{name:24s} {0:5d}")
            continue
        pt = float(np.mean([e.psnr_true_db for e in sel]))
        pe = float(np.mean([e.psnr_est_db for e in sel]))
        err = float(np.median([e.eye_err_m for e in sel]))
        gaze = float(np.median([e.gaze_err_deg for e in sel]))
        lines.append(f"{name:24s} {len(sel):5d} {err:9.2f} {gaze:8.1f} {pt:9.2f} {pe:9.2f} "
                     f"{pe - pt:+8.2f}")  # fmt: skip
    return "\n".join(lines)


def write_csv(path: Path, sights: list[Sight], egos: list[Ego]) -> None:
    import csv

    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["kind", "t_s", "viewer", "target", "position", "truth", "true_eye",
                    "estimated_eye", "eye_err_m", "gaze_err_deg", "in_gap"])  # fmt: skip
        for s in sights:
            row = [f"{s.truth:.3f}", f"{s.from_true:.3f}", f"{s.from_est:.3f}"]
            row += [f"{s.eye_err_m:.3f}", "", str(int(s.in_gap))]
            w.writerow(["sightline", f"{s.t_s:g}", s.viewer, s.target, s.position, *row])
        for e in egos:
            row = [
                f"{e.psnr_true_db:.2f}",
                f"{e.psnr_est_db:.2f}",
                f"{e.eye_err_m:.3f}",
                f"{e.gaze_err_deg:.1f}",
                str(int(e.in_gap)),
            ]
            w.writerow(["psnr_db", f"{e.t_s:g}", e.viewer, "", "actual", "", *row])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", type=Path, required=True, help="a reconstructed sim case folder")
    ap.add_argument("--people", type=Path, required=True, help="egosurg people's file for it")
    ap.add_argument("--roles-out", type=Path, default=Path("roles_by_truth.toml"),
                    help="where the named roles are written")  # fmt: skip
    ap.add_argument("--times", default="2:56:12", help="first:last:step, case seconds")
    ap.add_argument("--offset", default="1m left-posterior", help="the counterfactual position")
    ap.add_argument("--view-size", default="480x300", help="egocentric views, WxH (Table 4's)")
    ap.add_argument("--csv", type=Path, help="write every instant and view here")
    ap.add_argument("--naming", choices=("nearest", "longest"), default="nearest",
                    help="the truth's naming: the demo's (nearest tracks first), or each "
                    "person's longest non-overlapping tracks")  # fmt: skip
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.view_size.lower().split("x"))
    world, model_at, raster, times, _ = _case_source(args.case, _times(args.times))
    named = name_people(args.people, world, args.roles_out, args.naming)
    print(f"{args.people}: named by the sim's truth ({args.naming}; within 0.5 m, median): "
          + ", ".join(f"{n.track}={n.role} ({n.median_m:.2f} m)" for n in named))  # fmt: skip
    # the review tools' own check: a roles file made for another session is refused
    roles = list(CaseInputs(args.case).trajectories(args.roles_out))
    people = read_trajectory_file(args.people).trajectories
    for line in role_lines({n.track: n.role for n in named}, people):
        print("  " + line)
    paths = {r.name: CameraPath(r) for r in roles}
    answered = sum(estimated_pose(paths, n, float(t)) is not None
                   for t in times for n in world.head_poses(float(t)))  # fmt: skip
    print(
        f"  the roles give an eye at {answered} of "
        f"{sum(len(world.head_poses(float(t))) for t in times)} person-timestamps"
    )
    t0 = time.perf_counter()
    sights, egos = review(world, model_at, times, roles, raster, args.offset, (w, h))
    print(f"case {args.case}, {len(times)} timestamps ({times[0]:g}-{times[-1]:g} s), "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    print(los_table(sights, args.offset))
    refused = [s for s in sights if s.refused]
    if refused:
        print(
            f"the estimated eye inside a screen's box, where the sightline tool refuses (counted "
            f"as none of it seen): {len(refused)} instants "
            f"({', '.join(sorted({f'{s.viewer} at {s.t_s:g} s' for s in refused}))})"
        )
    print(ego_table(egos))
    if args.csv is not None:
        write_csv(args.csv, sights, egos)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
