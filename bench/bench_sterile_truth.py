"""Whose points each sterile-field event really was, from the simulator's truth: for every
contact event the detector reports (and every scripted touch it misses), the true surface
nearest each of its in-box points (a person's body, or a static object of the room: the drape,
the table, its padding) and how far that point lies from it, and how far outside the box the
attributed person's true body was. The detector reads each timestamp's stored-point evidence
as ``bench_sterile_evidence.py`` keeps it (``--evidence``, made there first); the truth is the
sim's ``World`` at the same time (``sim/contact.py``'s script on).

A missed touch is traced test by test: the stored points within 5 cm of the true body's part
inside the box, how many of them the static scene hides, and for the blob that holds them its
flicker share and each role's part (points in and out of the box, distance to the eye, rise).

Example (docs/replay.md, "Sterile field"; ``--variant`` judges with other detector settings)::

    .venv/bin/python bench/bench_sterile_truth.py --seed 7 --evidence ev7 --every 0.25 \\
        --from 30 --to 40 --roles roles7.toml --field field7.toml --truth truth7.csv \\
        --variant "max_role_distance_m=0.4"
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script from anywhere

from bench.bench_sterile import score
from bench.bench_sterile_evidence import STERILE, sights

SAMPLE_M = 0.01  # true surfaces sampled this densely (people); the room at twice it


def surface_samples(mesh, spacing_m: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) points spread over a triangle mesh's surface, about one per spacing squared."""
    tri = mesh.vertices.astype(float)[mesh.triangles]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = np.clip(np.ceil(area / spacing_m**2), 1, 200_000).astype(int)
    t = tri[np.repeat(np.arange(len(tri)), n)]
    r1, r2 = np.sqrt(rng.random(len(t))), rng.random(len(t))
    return ((1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1]
            + (r1 * r2)[:, None] * t[:, 2])  # fmt: skip


class SimTruth:
    """The sim's surfaces around a field: the room's static objects once, people per time."""

    def __init__(self, seed: int, region) -> None:
        from sim.world import World

        self.world = World.from_seed(seed, contact=True)
        self.rng = np.random.default_rng(0)
        self.room: dict[str, np.ndarray] = {}
        for k, obj in enumerate(self.world.static_objects):
            p = surface_samples(obj.mesh, 2 * SAMPLE_M, self.rng)
            p = p[region.holds(p)]
            if len(p):  # jittered: a flat face's exact duplicates make a degenerate k-d tree
                self.room[f"{obj.name}#{k}"] = p + 1e-5 * self.rng.standard_normal(p.shape)

    def people(self, t_s: float) -> dict[str, np.ndarray]:
        objects, _ = self.world._moving_objects(t_s)
        out: dict[str, list[np.ndarray]] = {}
        for obj in objects:
            out.setdefault(obj.name.split(":")[0], []).append(
                surface_samples(obj.mesh, SAMPLE_M, self.rng)
            )
        return {name: np.concatenate(parts) for name, parts in out.items()}

    def nearest(self, points_m: np.ndarray, t_s: float) -> tuple[list[str], np.ndarray]:
        """Each point's nearest true surface (a person or a room object) and its distance."""
        clouds = {**self.room, **self.people(t_s)}
        best, who = np.full(len(points_m), np.inf), np.zeros(len(points_m), int)
        for k, cloud in enumerate(clouds.values()):
            d, _ = cKDTree(cloud, balanced_tree=False).query(points_m)
            better = d < best
            best[better], who[better] = d[better], k
        names = list(clouds)
        return [names[i] for i in who], best


def load(args: argparse.Namespace, cfg):
    from protocol.formats.site import read_site
    from reconstructor.replay.sterile import Region

    box = next(iter(read_site(args.field).values()))
    region = Region(box, cfg)
    n = round((args.t_to - args.t_from) / args.every) + 1
    stamps, paths = [], []
    for k in range(n):
        t = round(args.t_from + k * args.every, 6)
        paths.append(Path(args.evidence) / f"t{t:09.3f}.npz")
        with np.load(paths[-1]) as z:
            pts = z["points_m"]
        stamps.append((t, pts[region.holds(pts)]))
    return box, region, stamps, paths


def trace_missed(region, bg, pts, eyes, t_s, near_true, cfg) -> list[str]:
    """The detector's tests, one by one, on the blobs holding the moving points ``near_true``."""
    from reconstructor.replay.sterile import _distance, _parts

    v = region.voxels(pts)
    moving = ~bg.static[v[:, 0], v[:, 1], v[:, 2]]
    pts, v, focus = pts[moving], v[moving], near_true[moving]
    inside = region.box.contains(pts)
    grid = np.zeros(region.shape, bool)
    grid[v[:, 0], v[:, 1], v[:, 2]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    label = labels[v[:, 0], v[:, 1], v[:, 2]]
    lines = []
    for k in np.unique(label[focus & inside]):
        whole = label == k
        flicker = float(np.median(bg.flicker(v[whole & inside], t_s, cfg.flicker_window_s)))
        lines.append(f"blob of {int(whole.sum())} points, {int((whole & inside).sum())} in the "
                     f"box, flicker {flicker:.2f} (max {cfg.max_flicker})")  # fmt: skip
        for role, sel in _parts(pts, v, whole, inside, eyes, True, cfg.voxel_m,
                                cfg.body_radius_m):  # fmt: skip
            n_in = int((sel & inside).sum())
            rise = pts[sel, 2].max() - eyes[role][2]
            lines.append(
                f"  {role}'s part: {n_in} in (min {cfg.min_points}), "
                f"{int(sel.sum()) - n_in} out (min {cfg.min_outside}), median distance to the "
                f"eye {_distance(pts[sel], eyes[role]):.2f} m (max {cfg.max_role_distance_m}), "
                f"top {rise:+.2f} m from the eye (min -{cfg.max_shoulder_drop_m}); "
                f"{int((sel & focus).sum())} of the true hand's points"
            )
    return lines


def main(argv: list[str] | None = None) -> int:
    from reconstructor.replay.sterile import (
        Instant,
        SterileConfig,
        background,
        group_events,
        moving_blobs,
    )
    from reconstructor.replay.sterile_run import _eyes, read_roles
    from reconstructor.replay.sterile_seen import freespace

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seed", type=int, required=True, help="the sim seed of the session")
    p.add_argument("--evidence", required=True, help="bench_sterile_evidence.py's folder")
    p.add_argument("--every", type=float, default=0.25)
    p.add_argument("--from", dest="t_from", type=float, required=True)
    p.add_argument("--to", dest="t_to", type=float, required=True)
    p.add_argument("--roles", required=True)
    p.add_argument("--field", required=True)
    p.add_argument("--truth", required=True)
    p.add_argument("--variant", default="", help='SterileConfig kwargs ("max_role_distance_m=0.4")')
    args = p.parse_args(argv)

    cfg = SterileConfig(sterile_roles=STERILE, **eval(f"dict({args.variant})", {"None": None}))
    box, region, stamps, files = load(args, cfg)
    paths = read_roles(args.roles, STERILE)
    times = [t for t, _ in stamps]
    eyes = [_eyes(paths, t) for t in times]
    bg = background(region, [pts for _, pts in stamps], times)
    free = freespace(region, sights(files), times)  # the seen-empty tests, as the tool runs them
    instants = [Instant(t, f"t{t:09.3f}", *moving_blobs(region, bg, pts, e, t, None, free))
                for (t, pts), e in zip(stamps, eyes, strict=True)]  # fmt: skip
    events = [e for e in group_events(box, instants, cfg, eyes) if not e.sterile_role]
    rows = [{"kind": "contact", "role": e.role, "start_s": f"{e.start_s:.3f}",
             "end_s": f"{e.end_s:.3f}"} for e in events]  # fmt: skip
    truth = [(r["person"], float(r["start_s"]), float(r["end_s"]))
             for r in csv.DictReader(open(args.truth))]  # fmt: skip
    sc = score(rows, truth, set(STERILE), times[0], times[-1], 0.5, "radiographer")
    false = {(role, start) for role, start, _ in sc.false}
    sim = SimTruth(args.seed, region)
    print(f"seed {args.seed}, {times[0]:g}-{times[-1]:g} s: recall {sc.found}/{sc.touches}, "
          f"{sc.false_events} false\n")  # fmt: skip
    print(
        "| event | role | t (s) | in-box points | nearest true surface (points) | median gap "
        "(cm) | depth in box (cm) | z (m) | role's true body in the box (cm, < 0: outside) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for e in events:
        verdict = "false" if (e.role, e.start_s) in false else "true"
        for inst, blob in zip(e.instants, e.blobs, strict=True):
            pin = blob.points_m[blob.in_field]
            names, gap = sim.nearest(pin, inst.t_s)
            kinds, counts = np.unique(names, return_counts=True)
            ranked = sorted(zip(counts, kinds, strict=True), reverse=True)
            who = ", ".join(f"{n} {c}" for c, n in ranked)
            body = sim.people(inst.t_s).get(e.role)  # none for "a person not followed"
            deepest = float(region.depth_inside(body).max()) if body is not None else np.nan
            print(f"| {verdict} | {e.role} | {inst.t_s:.2f} | {len(pin)} | {who} | "
                  f"{100 * np.median(gap):.1f} | {100 * np.median(region.depth_inside(pin)):.1f} "
                  f"| {np.median(pin[:, 2]):.2f} | {100 * deepest:.0f} |")  # fmt: skip
    for name, a, b in sc.missed:
        print(f"\nmissed: {name} {a:.3f}-{b:.3f} s")
        for k, t in enumerate(times):
            body = sim.people(t)[name]
            body = body[box.contains(body)]
            if not (a - args.every <= t <= b + args.every) or not len(body):
                continue
            pts = stamps[k][1]
            near = cKDTree(body).query(pts)[0] < 0.05
            v = region.voxels(pts)
            static = bg.static[v[:, 0], v[:, 1], v[:, 2]]
            inb = box.contains(pts)
            print(
                f"  {t:.2f} s: {int((near & inb).sum())} stored points within 5 cm of the "
                f"true hand in the box, {int((near & inb & static).sum())} of them static"
            )
            for line in trace_missed(region, bg, pts, eyes[k], t, near & ~static, cfg):
                print("    " + line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
