"""How much of each egocentric view the rig saw at all, from the simulator's exact geometry, and
how the reconstruction scores on what it saw against what it did not (the distance
to the egocentric goal).

For every reference view of a sim evaluation set: the view's true surface point at each pixel
(``World.render``'s depth), tested against each of the rig's eight sensors (an ideal pinhole
of its calibration, a quarter-size true depth map): the point is seen by a sensor when it
projects into its image and is not hidden there (within 3 cm + 1 % of its depth). A pixel is

- **seen by a stereo pair** when both sensors of one unit see it (what stereo depth, and so
  the fused points every model starts from, can hold);
- **seen once** when some sensor sees it but no pair does (colour, no stereo depth);
- **unseen** when no sensor does: whatever a model shows there is inferred.

With ``--scores OUT`` (an ``egosurg evaluate`` folder with the egocentric protocol) it also
reads each view's side-by-side picture (``OUT/egocentric/png``: reference, then each method)
and gives each method's PSNR over each kind of pixel (the label burned into each tile's top
left corner, 30 x 260 px, is left out of every sum).

Example::

    .venv/bin/python bench/bench_ego_coverage.py out/evalset_ego --scores out/dw/s2000_w0 \\
        --picture docs/ego_coverage.png
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.camera import Camera
from protocol.formats.eval_set import EvalSet, ReferenceView
from protocol.session import SessionReader
from sim.world import World

SHRINK = 4  # the sensors' true depth maps at a quarter size
LABEL_PX = (30, 260)  # rows, columns of each tile's burned-in label
KINDS = ("pair", "once", "unseen")
# footprint-ratio bins of the seen pixels: the rig sampled the surface at least as finely as
# the view does, up to twice / four times coarser, coarser still
RATIOS = (("r<=1", 0.0, 1.0), ("r1-2", 1.0, 2.0), ("r2-4", 2.0, 4.0), ("r>4", 4.0, np.inf))


@dataclass
class ViewCoverage:
    view: str
    phase: str
    role: str
    kind: np.ndarray  # (H, W) int: 0 pair, 1 once, 2 unseen, -1 no surface (never scored)
    ratio: np.ndarray  # (H, W) footprint ratio (``coverage``)

    def share(self, k: int) -> float:
        valid = self.kind >= 0
        return float(np.mean(self.kind[valid] == k)) if valid.any() else float("nan")


def _small(camera: Camera) -> Camera:
    return Camera(name=camera.name, intrinsics=camera.intrinsics.shrunk(SHRINK), pose=camera.pose)


def _seen(
    world: World, sensor: Camera, t_s: float, points_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """((N,) bool: which world points ``sensor`` sees unhidden at ``t_s``, (N,) their depth in
    it, m)."""
    cam = _small(sensor)
    depth = world.render(world.virtual_camera(cam.pose, cam.intrinsics, name="cov"), t_s).depth_m
    k = cam.intrinsics
    pc = points_w @ cam.pose.R.T + cam.pose.t_m
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(pc[:, 0] / z * k.fx_px + k.cx_px)
        v = np.rint(pc[:, 1] / z * k.fy_px + k.cy_px)
    inside = (z > 0.05) & (u >= 0) & (u < k.width_px) & (v >= 0) & (v < k.height_px)
    seen = np.zeros(len(points_w), bool)
    ui, vi = u[inside].astype(int), v[inside].astype(int)
    surface = depth[vi, ui]
    seen[inside] = np.abs(surface - z[inside]) < 0.03 + 0.01 * z[inside]
    return seen, z


def coverage(
    world: World, view: ReferenceView, t_s: float, train_scale: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) int: 0 seen by a stereo pair, 1 seen once, 2 unseen, -1 no surface;
    (H, W) float: the **footprint ratio**, the finest patch of surface one training pixel of a
    sensor that saw the point covers (depth / focal at ``train_scale`` of the sensor's width),
    over the patch one pixel of the view covers (inf where unseen): above 1 the view asks for
    detail finer than any training image holds)."""
    r = world.render(view.camera, t_s)
    k = view.camera.intrinsics
    h, w = r.depth_m.shape
    vv, uu = np.mgrid[0:h, 0:w]
    valid = np.isfinite(r.depth_m)
    z = r.depth_m[valid]
    pc = np.stack([(uu[valid] - k.cx_px) / k.fx_px * z, (vv[valid] - k.cy_px) / k.fy_px * z, z], 1)
    pw = (pc - view.camera.pose.t_m) @ view.camera.pose.R
    pair = np.zeros(len(pw), bool)
    once = np.zeros(len(pw), bool)
    finest = np.full(len(pw), np.inf)
    for unit in world.rig:
        sides = []
        for s in ("left", "right"):
            sensor = unit.sensor(s, "SVGA")
            seen, z_s = _seen(world, sensor, t_s, pw)
            foot = z_s / (sensor.intrinsics.fx_px * train_scale)
            finest = np.where(seen, np.minimum(finest, foot), finest)
            sides.append(seen)
        pair |= sides[0] & sides[1]
        once |= sides[0] | sides[1]
    kind = np.full((h, w), -1, np.int8)
    kind[valid] = np.where(pair, 0, np.where(once, 1, 2))
    ratio = np.full((h, w), np.inf)
    ratio[valid] = finest / (z / k.fx_px)
    return kind, ratio


def _tiles(png: Path, width: int) -> list[np.ndarray]:
    img = cv2.imread(str(png))[:, :, ::-1].astype(np.float64) / 255.0
    return [img[:, i : i + width] for i in range(0, img.shape[1], width)]


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    if not mask.any():
        return float("nan")
    mse = float(np.mean((a[mask] - b[mask]) ** 2))
    return 10 * np.log10(1 / mse) if mse > 0 else float("inf")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("eval_set", type=Path, help="a sim evaluation set (egosurg sim eval-set)")
    ap.add_argument("--scores", type=Path, help="an egosurg evaluate folder (egocentric)")
    ap.add_argument("--csv", type=Path, help="write one row per view here")
    ap.add_argument("--picture", type=Path,
                    help="3 views: reference | render | who saw it | footprint ratio")  # fmt: skip
    ap.add_argument("--train-width", type=int, default=480,
                    help="the scores' training width, px (the sensors: 960)")  # fmt: skip
    args = ap.parse_args()
    es = EvalSet.read(args.eval_set)
    methods: list[str] = []
    scored: dict[tuple[str, str, str], float] = {}  # (scene@set, view, method) -> PSNR, dB
    if args.scores:
        with open(args.scores / "egocentric" / "scores.csv") as fh:
            for r in csv.DictReader(fh):
                methods.append(r["method"])
                scene_at = r["scene"].split("/")[0]
                scored[(scene_at, r["view"], r["method"])] = float(r["psnr_db"])
        methods = list(dict.fromkeys(methods))
    missing = 0
    rows, covs, pictures = [], [], []
    for scene in es.scenes:
        if not scene.views:
            continue
        with SessionReader(es.path(scene.session)) as reader:
            meta, start = reader.info.case_metadata, reader.info.started_unix_ns
            set_ns = reader.sets().set_unix_ns
        world = World.from_seed(int(meta["seed"]), phase=meta["phase"])
        for view in scene.views:
            t_s = (int(set_ns[view.set_index]) - start) / 1e9  # session time = sim time
            cov = ViewCoverage(view.name, scene.phase, view.role,
                               *coverage(world, view, t_s, args.train_width / 960))  # fmt: skip
            covs.append(cov)
            row = {"scene": f"{scene.name}@set{view.set_index}", "view": view.name,
                   "phase": scene.phase, "role": view.role,
                   **{f"{k}_share": cov.share(i) for i, k in enumerate(KINDS)}}  # fmt: skip
            seen = (cov.kind >= 0) & (cov.kind < 2)
            for name, lo, hi in RATIOS:
                band = (cov.ratio[seen] > lo) & (cov.ratio[seen] <= hi)
                row[f"{name}_share"] = float(np.mean(band))
            for m in methods:  # the evaluation's own score of the whole view
                row[f"{m}_psnr"] = scored.get((row["scene"], view.name, m), np.nan)
            png = (
                args.scores / "egocentric" / "png" / _png_name(scene.name, view)
                if args.scores
                else None
            )
            if png is not None and not png.is_file():
                missing += 1  # a run whose pictures stayed elsewhere: coverage and score only
            elif png is not None:
                ref, *renders = _tiles(png, view.camera.intrinsics.width_px)
                keep = np.ones(cov.kind.shape, bool)
                keep[: LABEL_PX[0], : LABEL_PX[1]] = False
                for m, img in zip(methods, renders, strict=False):
                    row[f"{m}_all"] = _psnr(img, ref, keep)
                    for i, k in enumerate(KINDS):
                        row[f"{m}_{k}"] = _psnr(img, ref, keep & (cov.kind == i))
                    for name, lo, hi in RATIOS:
                        band = seen & (cov.ratio > lo) & (cov.ratio <= hi)
                        row[f"{m}_{name}"] = _psnr(img, ref, keep & band)
                if len(pictures) < 3 and view.role in ("surgeon", "anaesthetist", "circulator"):
                    pictures.append((view.name, ref, renders[-1] if renders else ref, cov))
            rows.append(row)
            shares = " ".join(f"{k} {row[f'{k}_share']:.2f}" for k in KINDS)
            print(f"{row['scene']:28s} {view.name:20s} {shares}", flush=True)
    if missing:
        print(f"\n{missing} of {len(rows)} views have no side-by-side picture in {args.scores}: "
              "PSNR by kind of pixel is over the other views only")  # fmt: skip
    _report(rows, methods)
    if args.csv:
        with args.csv.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
            w.writeheader()
            w.writerows(rows)
    if args.picture and pictures:
        _picture(args.picture, pictures)
        print(f"wrote {args.picture}")


def _png_name(scene: str, view: ReferenceView) -> str:
    raw = f"{scene}_set{view.set_index}_{view.name}"
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in raw) + ".png"


def _mean(rows: list[dict], key: str) -> str:
    v = np.array([r[key] for r in rows if np.isfinite(r.get(key, np.nan))])
    return f"{v.mean():.2f} ± {v.std(ddof=1):.2f}" if len(v) > 1 else "—"


def _report(rows: list[dict], methods: list[str]) -> None:
    print(f"\n{len(rows)} views: share of the pixels with a surface, mean ± SD over views")
    print("| group | views | seen by a pair | seen once | unseen |")
    print("|---|---|---|---|---|")
    groups = [("all", rows)]
    for key in ("phase", "role"):
        values = dict.fromkeys(r[key] for r in rows)
        groups += [(v, [r for r in rows if r[key] == v]) for v in values]
    for name, sel in groups:
        cells = " | ".join(_mean(sel, f"{k}_share") for k in KINDS)
        print(f"| {name} | {len(sel)} | {cells} |")
    bands = [n for n, _, _ in RATIOS]

    def band_table(title: str, prefix: str) -> None:
        print(f"\n{title}")
        print("| group | " + " | ".join(bands) + " |")
        print("|---|" + "---|" * len(bands))
        for name, sel in groups:
            cells = [_mean(sel, prefix.format(n)) for n in bands]
            print(f"| {name} | " + " | ".join(cells) + " |")

    band_table("seen pixels by footprint ratio (the finest training pixel over the view's pixel)",
               "{}_share")  # fmt: skip
    for m in methods:
        band_table(f"{m}: PSNR (dB) over seen pixels by footprint ratio, mean ± SD over views",
                   f"{m}_{{}}")  # fmt: skip
    for m in methods:
        share = np.array([r["r>4_share"] for r in rows])
        psnr = np.array([r.get(f"{m}_psnr", np.nan) for r in rows])
        ok = np.isfinite(share) & np.isfinite(psnr)
        if ok.sum() > 2:
            slope, icept = np.polyfit(share[ok], psnr[ok], 1)
            corr = np.corrcoef(share[ok], psnr[ok])[0, 1]
            fit = f"r = {corr:.2f}, PSNR = {icept:.1f} {slope:+.1f} x share"
            print(f"\n{m}: whole-view PSNR against the share of seen pixels above ratio 4, over "
                  f"{ok.sum()} views: {fit}")  # fmt: skip
        print(f"\n{m}: PSNR (dB) over each kind of pixel, mean ± SD over views")
        print("| group | scored (whole view) | all pixels (pictured views) | seen by a pair | "
              "seen once | unseen |")  # fmt: skip
        print("|---|---|---|---|---|---|")
        for name, sel in groups:
            cells = [_mean(sel, f"{m}_{k}") for k in ("psnr", "all", *KINDS)]
            print(f"| {name} | " + " | ".join(cells) + " |")


def _picture(path: Path, pictures: list) -> None:
    colours = np.array([[0.2, 0.7, 0.3], [0.95, 0.75, 0.2], [0.85, 0.2, 0.2]])
    lines = []
    for name, ref, render, cov in pictures:
        kind = cov.kind
        over = ref.copy()
        for i in range(3):
            over[kind == i] = 0.45 * ref[kind == i] + 0.55 * colours[i]
        # the footprint ratio, log2 from 0 (as fine as the view) to 4 (16 times coarser)
        level = np.clip(np.log2(np.maximum(cov.ratio, 1.0)) / 4.0, 0, 1)
        heat = cv2.applyColorMap((level * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        heat = heat[:, :, ::-1].astype(np.float64) / 255.0
        heat[~np.isfinite(cov.ratio)] = 0.25
        tiles = [ref, render, over, heat]
        row = np.concatenate([np.ascontiguousarray((t * 255).astype(np.uint8)[:, :, ::-1])
                              for t in tiles], axis=1)  # fmt: skip
        cv2.putText(row, name, (8, row.shape[0] - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.9,
                    (255, 255, 255), 2)  # fmt: skip
        lines.append(row)
    path.parent.mkdir(parents=True, exist_ok=True)
    full = np.concatenate(lines, axis=0)
    half = cv2.resize(full, (full.shape[1] // 2, full.shape[0] // 2), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), half)


if __name__ == "__main__":
    main()
