"""What a denser stereo config adds on the sim, how wrong it is, and where the egocentric views
see it: the trace behind EVALUATION.md's "Why the densest config loses egocentric PSNR".

At the instants the downstream comparison scored (``bench/bench_stereo_downstream.py``'s
evaluation set: seed 3, t = 2 s, SVGA, JPEG 90, set 0 of setup, intraoperative and turnover),
every camera's depth is made as ``egosurg evaluate`` makes it (``stereo_clouds``: the matcher,
then the fill stage) with a base config and the others, and judged against the sim's true
depth along each point's ray (the nearest truth pixel of the left sensor image; depth edges
included):

1. the pixels each config answers that the base does not (and those it drops), by surface kind
   (a person's silhouette band, the rest of a person, the blank walls and ceiling, the floor,
   equipment), with the share of their depths more than 3 % off, and what the base's fill stage
   (at every pixel) puts there instead and how much of that is more than 3 % off;
2. the fill stage's points as the pipeline makes them (stride 2, the shell at 4);
3. the wrong answers (> 3 % off) in every egocentric view of the instant: the ones in its
   frustum in front of the surface the view sees there (floaters it looks through), and the
   share of the view's pixels they cover;
4. the fused cloud (``fuse`` with the config's cap, and with ``--uncapped`` without one) in
   every egocentric view: points on the surface it sees (within 3 %), floating in front of it,
   and behind it.

    nice -n 10 .venv/bin/python bench/bench_stereo_added.py --uncapped \\
        --picture docs/stereo_added.png [--phases setup,intraoperative,turnover] \\
        [--configs default=docs/evaluation_cpu.toml,densest=bench/configs/stereo_densest.toml]

``--shell-rule TAU`` adds a row: the second config without the answers it adds that lie
within TAU of the room's shell along their ray, so that the fill stage puts the shell there
(the rule tried in EVALUATION.md; measured on the depth and the fused cloud, not trained).

``--picture`` draws one camera (``--picture-at PHASE/SERIAL``): its rectified left image in
grey, the base's answers tinted blue, the pixels the second config adds coloured by their error.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_stereo import CachedSgbm, as_recorded, with_fill
from protocol.camera import Camera, Pose
from reconstructor.config import ReconstructConfig
from reconstructor.depth.fill import fill_points_in_world, ray_box_exit
from reconstructor.depth.fusion import fuse
from reconstructor.depth.stereo import DepthMap, compute_depth

KINDS = ("person edge", "person", "blank", "floor", "equipment")
BLANK = ("walls", "ceiling", "ceiling_panel")
EDGE_PX = 3  # a person's silhouette band: this many sensor pixels either side of its outline
OFF = 0.03  # a depth is wrong when more than this share off the truth
VIEW_SIZE_PX = (480, 300)  # the evaluation set's egocentric views (bench_stereo_downstream)
VIEW_HFOV_DEG = 90.0
UNCAPPED = 10_000_000  # ``--uncapped``: a cap no timestamp reaches
SNAP = (0.05, 0.1, 0.2, 0.5)  # table 5: answers this near the room's shell moved onto it


@dataclass
class CameraDepth:
    """One camera's depth under one config: each rectified pixel's error and surface kind, and
    the world points of its answers and of its fill stage."""

    depth: DepthMap
    rel_err: np.ndarray  # (H, W) |z - z_true| / z_true of the answers, NaN elsewhere
    fill_rel_err: np.ndarray  # (H, W) the same for the fill stage's depth (stride 1)
    kind: np.ndarray  # (H, W) index into KINDS of every pixel, -1 where nothing was hit
    answers: tuple[np.ndarray, np.ndarray]  # world points (row-major valid pixels), colours
    fill: tuple[np.ndarray, np.ndarray]  # the fill stage's world points and colours
    fill_err: np.ndarray  # (F,) their errors
    # tau -> (H, W) the answers' errors with each answer within tau of the room's shell along
    # its ray moved onto it
    snapped_err: dict[float, np.ndarray]


def sensor_kinds(names: list[str], object_index: np.ndarray) -> np.ndarray:
    """(H, W) index into KINDS of every sensor pixel (-1 where nothing was hit)."""
    lut = []
    for n in names:
        if ":" in n:  # "<person>:<material>"
            lut.append(KINDS.index("person"))
        elif n in BLANK:
            lut.append(KINDS.index("blank"))
        elif n == "floor":
            lut.append(KINDS.index("floor"))
        else:
            lut.append(KINDS.index("equipment"))
    kind = np.array([*lut, -1])[np.clip(object_index.astype(int), -1, len(names))]
    kind[object_index < 0] = -1
    person = (kind == KINDS.index("person")).astype(np.uint8)
    k = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)
    band = (cv2.dilate(person, k) > 0) & (cv2.erode(person, k) == 0)
    kind[band] = KINDS.index("person edge")
    return kind


def errors_at(
    points_left: np.ndarray, sensor, truth_m: np.ndarray, kinds: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each left-camera point's |z - z_true| / z_true at its nearest sensor pixel, and the
    surface kind there (NaN / -1 outside the image or where nothing was hit)."""
    n = len(points_left)
    err, kind = np.full(n, np.nan), np.full(n, -1)
    if not n:
        return err, kind
    cam = Camera(name="left", intrinsics=sensor, pose=Pose(R=np.eye(3)))
    px, z = cam.project(points_left.astype(np.float64))
    h, w = truth_m.shape
    u, v = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0)
    zt = truth_m[v[inside], u[inside]].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        err[inside] = np.where(np.isfinite(zt), np.abs(z[inside] - zt) / zt, np.nan)
    kind[inside] = kinds[v[inside], u[inside]]
    return err, kind


def per_pixel(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = np.full(mask.shape, np.nan)
    out[mask] = values
    return out


def camera_depth(
    left_rgb, right_rgb, unit, st, cfg: ReconstructConfig, truth_m, kinds
) -> CameraDepth:
    """One camera's depth and fill under ``cfg``, judged against ``truth_m``."""
    assert cfg.stereo is not None
    d = compute_depth(
        left_rgb, right_rgb, st.left, st.right, st.right_from_left, cfg.stereo,
        CachedSgbm(cfg.stereo),
    )  # fmt: skip
    return judged(d, unit, st, cfg, truth_m, kinds)


def shell_depth(d: DepthMap, left_pose: Pose, box) -> np.ndarray:
    """(H, W) the rectified depth at which each pixel's ray leaves the room's ``box``."""
    v, u = np.indices(d.valid.shape).reshape(2, -1)
    k = d.intrinsics
    rays = np.stack([(u - k.cx_px) / k.fx_px, (v - k.cy_px) / k.fy_px, np.ones(len(u))], 1)
    centre = left_pose.centre_m
    world = (rays @ d.rect_from_left - left_pose.t_m) @ left_pose.R
    lo, hi = np.asarray(box[0]), np.asarray(box[1])
    return ray_box_exit(centre, world - centre, lo, hi).reshape(d.valid.shape)


def left_to_shell(
    cd: CameraDepth, base: CameraDepth, tau: float, unit, st, cfg, truth_m, kinds
) -> CameraDepth:
    """``--shell-rule``: ``cd`` without the answers it adds to ``base`` that lie within ``tau``
    of the room's shell along their ray (the fill stage puts the shell there instead)."""
    d = cd.depth
    shell = shell_depth(d, unit.left_pose, cfg.room_box_m)
    with np.errstate(invalid="ignore"):
        near = np.abs(d.depth_m - shell) <= tau * shell
    drop = d.valid & ~base.depth.valid & near
    kept = replace(d, valid=d.valid & ~drop, depth_m=np.where(drop, np.nan, d.depth_m))
    return judged(kept, unit, st, cfg, truth_m, kinds)


def judged(d: DepthMap, unit, st, cfg: ReconstructConfig, truth_m, kinds) -> CameraDepth:
    """``d`` with the fill stage ``cfg`` gives it, judged against ``truth_m``."""
    assert cfg.stereo is not None
    pts_left, colours = d.points_in_left_camera()
    err, _ = errors_at(pts_left, st.left, truth_m, kinds)
    fill = fill_points_in_world(
        d, unit.left_pose, cfg.fill, min_depth_m=cfg.stereo.min_depth_m,
        max_depth_m=cfg.stereo.max_depth_m, room_box_m=cfg.room_box_m,
    )  # fmt: skip
    fill_err, _ = errors_at(unit.left_pose.transform(fill[0]), st.left, truth_m, kinds)
    # the fill stage at every pixel: what it puts where this config has no answer
    filled = with_fill(d, cfg.stereo, "shell", unit.left_pose, cfg.room_box_m)
    fe, _ = errors_at(filled.points_in_left_camera()[0], st.left, truth_m, kinds)
    fill_rel = per_pixel(fe, filled.valid)
    fill_rel[d.valid] = np.nan
    # every rectified pixel's surface kind, through its ray at unit depth
    v, u = np.indices(d.valid.shape).reshape(2, -1)
    k = d.intrinsics
    rays = np.stack([(u - k.cx_px) / k.fx_px, (v - k.cy_px) / k.fy_px, np.ones(len(u))], 1)
    _, kind = errors_at(rays @ d.rect_from_left, st.left, truth_m, kinds)
    return CameraDepth(
        snapped_err=snapped(d, unit.left_pose, cfg.room_box_m, rays, st.left, truth_m, kinds),
        depth=d,
        rel_err=per_pixel(err, d.valid),
        fill_rel_err=fill_rel,
        kind=kind.reshape(d.valid.shape),
        answers=(d.points_in_world(unit.left_pose)[0], colours),
        fill=fill,
        fill_err=fill_err,
    )


def snapped(d: DepthMap, left_pose: Pose, box, rays, sensor, truth_m, kinds) -> dict:
    """Table 5: for each tau of SNAP, every answer's error once the answers within tau of the
    room's shell (where the pixel's ray leaves ``box``) are moved onto it."""
    if box is None:
        return {}
    valid = d.valid.reshape(-1)
    r = rays[valid]
    centre = left_pose.centre_m
    world = (r @ d.rect_from_left - left_pose.t_m) @ left_pose.R  # the rays at z = 1, world
    shell = ray_box_exit(centre, world - centre, np.asarray(box[0]), np.asarray(box[1]))
    z = d.depth_m[d.valid].astype(np.float64)
    out = {}
    for tau in SNAP:
        zz = np.where(np.abs(z - shell) <= tau * shell, shell, z)
        err, _ = errors_at((r * zz[:, None]) @ d.rect_from_left, sensor, truth_m, kinds)
        out[tau] = per_pixel(err, d.valid)
    return out


def in_view(points_world: np.ndarray, cam: Camera, truth_m: np.ndarray):
    """Per point, in ``cam``'s frustum: nearer than the surface the view sees there by more than
    OFF ('front'), within it ('on'), beyond it ('behind'); and each point's view pixel."""
    if not len(points_world):
        none = np.zeros(0, bool)
        return none, none, none, np.zeros(0, int)
    px, z = cam.project(points_world.astype(np.float64))
    h, w = truth_m.shape
    u, v = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0.05)
    zt = np.full(len(z), np.inf)
    zt[inside] = truth_m[v[inside], u[inside]]
    front = inside & (z < zt * (1 - OFF))
    on = inside & (np.abs(z - zt) <= OFF * zt)
    return front, on, inside & ~front & ~on, v * w + u


def view_share(mask: np.ndarray, pixel: np.ndarray, truth_m: np.ndarray) -> float:
    return len(np.unique(pixel[mask])) / truth_m.size


class Tally:
    """The tables' sums over cameras and phases."""

    def __init__(self) -> None:
        self.pixels: dict[tuple[str, str, str], np.ndarray] = defaultdict(lambda: np.zeros(5))
        self.fill: dict[tuple[str, str], np.ndarray] = defaultdict(lambda: np.zeros(3))
        self.ego: dict[tuple[str, str, str], np.ndarray] = {}
        self.fused: dict[tuple[str, str], np.ndarray] = {}
        self.snap: dict[tuple[str, float, str], np.ndarray] = defaultdict(lambda: np.zeros(2))

    def add_pixels(self, key, mask: np.ndarray, src: CameraDepth, base: CameraDepth) -> None:
        e = src.rel_err[mask]
        e = e[np.isfinite(e)]
        fe = base.fill_rel_err[mask]
        fe = fe[np.isfinite(fe)]
        self.pixels[key] += [mask.sum(), len(e), (e > OFF).sum(), len(fe), (fe > OFF).sum()]

    def camera(self, names: list[str], cds: dict[str, CameraDepth], phase: str) -> None:
        base = cds[names[0]]
        for name in names[1:]:
            cd = cds[name]
            added = cd.depth.valid & ~base.depth.valid
            dropped = base.depth.valid & ~cd.depth.valid
            for label, mask, src in (("added", added, cd), ("dropped", dropped, base)):
                for ki, kname in enumerate(KINDS):
                    self.add_pixels((name, label, kname), mask & (cd.kind == ki), src, base)
                self.add_pixels((name, label, "all"), mask, src, base)
            for tau, err in cd.snapped_err.items():
                for ki, kname in [*enumerate(KINDS), (None, "all")]:
                    m = added if ki is None else added & (cd.kind == ki)
                    e = err[m]
                    e = e[np.isfinite(e)]
                    self.snap[(name, tau, kname)] += [len(e), (e > OFF).sum()]
        for name in names:
            cd = cds[name]
            self.add_pixels((name, "answers", "all"), cd.depth.valid, cd, cd)
            fe = cd.fill_err[np.isfinite(cd.fill_err)]
            self.fill[(name, phase)] += [len(cd.fill_err), len(fe), (fe > OFF).sum()]

    def views(self, names, per_cfg, views, phase: str) -> None:
        """Table 3: each config's wrong answers (and those the base lacks) in every view."""
        for name in names:
            wrong, new = [], []
            for cd, base in zip(per_cfg[name], per_cfg[names[0]], strict=True):
                e = cd.rel_err[cd.depth.valid]
                bad = np.isfinite(e) & (e > OFF)
                wrong.append(cd.answers[0][bad])
                new.append(cd.answers[0][bad & ~base.depth.valid[cd.depth.valid]])
            for role, (cam, truth) in views.items():
                fa, _, _, pa = in_view(np.concatenate(wrong), cam, truth)
                fn, _, _, pn = in_view(np.concatenate(new), cam, truth)
                self.ego[(name, phase, role)] = np.array(
                    [fa.sum(), view_share(fa, pa, truth), fn.sum(), view_share(fn, pn, truth)]
                )

    def fusion(self, name: str, cfg: ReconstructConfig, cds: list[CameraDepth], views, phase):
        """Table 4: the fused cloud in every view."""
        fused = fuse([c for cd in cds for c in (cd.answers, cd.fill)], cfg.fusion)
        for role, (cam, truth) in views.items():
            front, on, behind, pix = in_view(fused.points_m, cam, truth)
            self.fused[(name, f"{phase}/{role}")] = np.array(
                [fused.stats["after_voxel"], on.sum(), front.sum(), behind.sum(),
                 view_share(on, pix, truth), view_share(front, pix, truth)]
            )  # fmt: skip


def pct(a: float, b: float) -> str:
    return f"{100 * a / b:.1f}" if b else "-"


def print_tables(t: Tally, base_name: str) -> None:
    print(f"\n1. Rectified pixels each config answers, adds to and drops from {base_name}'s, by "
          "surface kind (all cameras and phases):\n")  # fmt: skip
    print(f"| config | pixels | kind | pixels | with a truth | > 3 % off (%) | {base_name}'s "
          "fill there (% of them) | that fill > 3 % off (%) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for (name, label, kname), (n, nt, nb, nf, nfb) in t.pixels.items():
        fill = f"{pct(nf, n)} | {pct(nfb, nf)}" if label == "added" else " | "
        print(f"| {name} | {label} | {kname} | {int(n)} | {int(nt)} | {pct(nb, nt)} | {fill} |")
    print("\n2. The fill stage's points as the pipeline makes them:\n")
    print("| config | phase | fill points | > 3 % off (%) |\n|---|---|---|---|")
    for (name, phase), (n, nt, nb) in t.fill.items():
        print(f"| {name} | {phase} | {int(n)} | {pct(nb, nt)} |")
    print(
        "\n3. Wrong answers (> 3 % off) in front of the surface each egocentric view sees: all "
        "of a config's, and those the base lacks (points; share of the view's pixels):\n"
    )
    print("| config | view | wrong in front | view % | new wrong in front | view % |")
    print("|---|---|---|---|---|---|")
    for (name, phase, role), r in t.ego.items():
        print(f"| {name} | {phase}/{role} | {int(r[0])} | {100 * r[1]:.1f} | {int(r[2])} | "
              f"{100 * r[3]:.1f} |")  # fmt: skip
    if t.snap:
        print("\n5. The added answers within tau of the room's shell moved onto it (> 3 % off):\n")
        print("| config | tau | " + " | ".join(KINDS) + " | all |")
        print("|---|---|" + "---|" * (len(KINDS) + 1))
        for name, tau in dict.fromkeys((n, tau) for n, tau, _ in t.snap):
            cells = [pct(*t.snap[(name, tau, k)][::-1]) for k in (*KINDS, "all")]
            print(f"| {name} | {tau:g} | " + " | ".join(cells) + " |")
    if not t.fused:
        return
    print("\n4. The fused cloud in each egocentric view: points within 3 % of the surface the "
          "view sees (on), in front of it, behind it; the view's pixels with a point on / in "
          "front of the surface (%):\n")  # fmt: skip
    print("| config | view | voxels before the cap | on | front | behind | on px % | front px % "
          "| front / (on + front) % |\n|---|---|---|---|---|---|---|---|---|")  # fmt: skip
    sums: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(3))
    for (name, view), r in t.fused.items():
        print(f"| {name} | {view} | {int(r[0])} | {int(r[1])} | {int(r[2])} | {int(r[3])} | "
              f"{100 * r[4]:.1f} | {100 * r[5]:.1f} | {pct(r[2], r[1] + r[2])} |")  # fmt: skip
        sums[name] += r[1:4]
    for name, (on, front, behind) in sums.items():
        print(
            f"| {name} | all views | | {int(on)} | {int(front)} | {int(behind)} | | | "
            f"{pct(front, on + front)} |"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--configs",
        default="default=docs/evaluation_cpu.toml,densest=bench/configs/stereo_densest.toml",
        help="NAME=CONFIG,...: the first is the base",
    )
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--t-s", type=float, default=2.0)
    ap.add_argument("--phases", default="setup,intraoperative,turnover")
    ap.add_argument("--uncapped", action="store_true", help="also fuse without the cap")
    ap.add_argument("--no-fusion", action="store_true", help="skip table 4")
    ap.add_argument(
        "--shell-rule",
        type=float,
        default=0.0,
        metavar="TAU",
        help="also the second config without its added answers within TAU of the room's shell",
    )
    ap.add_argument("--picture", type=Path, help="draw one camera's added pixels (PNG)")
    ap.add_argument("--picture-at", default="turnover/43841101", metavar="PHASE/SERIAL")
    args = ap.parse_args()

    from sim import World
    from sim.eval_set import room_bounds

    configs: dict[str, ReconstructConfig] = {}
    for spec in args.configs.split(","):
        name, _, path = spec.partition("=")
        if not Path(path).is_file():
            print(f"--configs: no config file {path!r} for {name!r}", file=sys.stderr)
            return 2
        configs[name] = ReconstructConfig.read(path)
    if len(configs) < 2:
        print("--configs: give a base and at least one other, NAME=CONFIG,...", file=sys.stderr)
        return 2
    names = list(configs)
    if args.shell_rule:
        names.append(f"{names[1]}, added near the shell left to it")
    tally = Tally()
    for phase in args.phases.split(","):
        world = World.from_seed(args.seed, phase=phase)
        bounds = {"room_bounds_m": list(room_bounds(world))}
        resolved = {n: c.overridden(bounds, "the scene's room box") for n, c in configs.items()}
        views = {}
        for role, pose in world.head_poses(args.t_s).items():
            cam = world.virtual_camera(pose, hfov_deg=VIEW_HFOV_DEG, size_px=VIEW_SIZE_PX)
            views[role] = (cam, world.render(cam, args.t_s).depth_m)
        objects = [o.name for o in world.scene_at(args.t_s).objects]
        per_cfg: dict[str, list[CameraDepth]] = defaultdict(list)
        for unit in world.rig:
            left, right = world.render_stereo(unit, args.t_s, "SVGA")
            kinds = sensor_kinds(objects, left.object_index)
            st = unit.factory.stereo("SVGA")
            cds = {
                n: camera_depth(
                    as_recorded(left.image_rgb, 90),
                    as_recorded(right.image_rgb, 90),
                    unit,
                    st,
                    c.resolved(st.left.width_px),
                    left.depth_m,
                    kinds,
                )
                for n, c in resolved.items()
            }
            if args.shell_rule:
                n = f"{names[1]}, added near the shell left to it"
                cfg = resolved[names[1]].resolved(st.left.width_px)
                cds[n] = left_to_shell(
                    cds[names[1]], cds[names[0]], args.shell_rule, unit, st, cfg,
                    left.depth_m, kinds,
                )  # fmt: skip
            tally.camera(names, cds, phase)
            for n in names:
                per_cfg[n].append(cds[n])
            if args.picture and args.picture_at == f"{phase}/{unit.serial}":
                picture(args.picture, cds[names[1]], cds[names[0]])
            print(f"  {phase} SN{unit.serial} done", flush=True)
        tally.views(names, per_cfg, views, phase)
        for n in [] if args.no_fusion else names:
            cfg = resolved.get(n, resolved[names[1]])
            tally.fusion(n, cfg, per_cfg[n], views, phase)
            if args.uncapped:
                nocap = replace(cfg, fusion=replace(cfg.fusion, max_points=UNCAPPED))
                tally.fusion(f"{n}, no cap", nocap, per_cfg[n], views, phase)
        print(f"{phase} done", flush=True)
    print_tables(tally, names[0])
    return 0


def picture(path: Path, cd: CameraDepth, base: CameraDepth) -> None:
    """The rectified left image in grey; the base's answers tinted blue; the pixels ``cd`` adds
    by error: green within 1 %, yellow 1-3 %, orange 3-10 %, red beyond."""
    added = cd.depth.valid & ~base.depth.valid
    grey = cv2.cvtColor(cd.depth.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) * 0.6
    img = np.repeat(grey[:, :, None], 3, axis=2)
    img[base.depth.valid] = 0.7 * img[base.depth.valid] + 0.3 * np.array([60, 90, 200])
    e = np.nan_to_num(cd.rel_err, nan=1.0)
    for m, colour in (
        (added & (e <= 0.01), (0, 200, 0)),
        (added & (e > 0.01) & (e <= OFF), (230, 220, 0)),
        (added & (e > OFF) & (e <= 0.10), (255, 140, 0)),
        (added & (e > 0.10), (255, 0, 0)),
    ):
        img[m] = colour
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.clip(img, 0, 255).astype(np.uint8)[:, :, ::-1])
    print(f"wrote {path}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
