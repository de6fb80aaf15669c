"""The sterile-field detector's settings, one change at a time, on what the cameras saw: each
timestamp's evidence made as ``egosurg reconstruct`` stores it (stereo at the config's
settings, then ``reconstructor/depth/evidence.py``), without fusion or training, which the
detector does not read.

A case stores the same points with each model (``reconstructor/case/work.py``); this skips
the two stages a sterile review does not need (fusion was 44 s of a 90 s timestamp on a loaded
2-core machine) so that three seeds fit an evening. Each timestamp's evidence is kept in
``--evidence DIR`` (one ``.npz`` a timestamp): a rerun with other detector settings reads it
back. It also measures the matcher's disparity noise where the truth is known: the sim's floor
(z = 0), over every timestamp.

Each timestamp's evidence keeps which cameras saw each cell and where those cameras are, for
the seen-empty tests (``reconstructor/replay/sterile_seen.py``); ``--show-events`` lists each
contact with its peak part's points in and out of the box, the share of its in-box points in
air (seen through at 30 % or more of the other timestamps) and seen through now. Evidence made
before the masks is refused: make it again.

Each ``--variant`` is ``SterileConfig`` keyword arguments (``"margin_sigmas=0"``); the first row
is the defaults. Scored against the sim's truth as ``bench_sterile.py`` does (recall on the
scripted person's touches, false events of anyone non-sterile, start errors).

Example (the session, roles and truth made by docs/replay.md's commands)::

    .venv/bin/python bench/bench_sterile_evidence.py es11/intraoperative/session.h5 \\
        --config full.toml --every 0.25 --from 2 --to 62 --evidence ev11 --roles roles11.toml \\
        --field field11.toml --truth truth11.csv --label "seed 11" --variant "margin_sigmas=0"
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script from anywhere

from bench.bench_sterile import score

STERILE = ("surgeon", "assistant", "nurse_scrub")


def _evidence_one(job: tuple[str, str, str, float, str]) -> str:
    """Compute and keep one timestamp's evidence (in a worker process)."""
    from protocol.formats.rig_calibration import RigCalibration
    from reconstructor.config import ReconstructConfig
    from reconstructor.data.frames import load_timestamp
    from reconstructor.depth.evidence import observed_of_reconstruction
    from reconstructor.pipeline import stereo_clouds

    session, calibration, config_toml, t_s, out = job
    ts = load_timestamp(session, RigCalibration.read(calibration), float(t_s))
    text = Path(config_toml).read_text() if config_toml else ""
    cfg = ReconstructConfig.from_toml(text, config_toml or "defaults")
    cfg = cfg.resolved(ts.frames[0].camera.intrinsics.width_px)
    _, depths = stereo_clouds(ts, cfg)
    seen = observed_of_reconstruction(depths, ts.stereo_pairs())
    poses = {f"SN{left.camera_serial}": left.camera.pose for left, _ in ts.stereo_pairs()}
    floor = np.concatenate([floor_disparity_errors(d, poses[n]) for n, d in depths.items()])
    tmp = Path(out).with_suffix(".tmp.npz")
    centres = np.stack([poses[n].centre_m for n in seen.cameras]) if seen.cameras else None
    np.savez(tmp, points_m=seen.points_m, m_per_px=seen.m_per_px, t_s=ts.t_s,
             floor_err_px=floor[::25].astype(np.float32), seen_by=seen.seen_by,
             cameras=np.array(seen.cameras), camera_centres_m=centres)  # fmt: skip
    tmp.replace(out)
    return out


def floor_disparity_errors(depth, pose, band_m: float = 0.2) -> np.ndarray:
    """(M,) disparity errors (px) of the depth map's pixels that see the sim's floor (z = 0
    exactly; points within ``band_m`` of it): the measured disparity minus the one of the
    depth at which the pixel's ray meets the floor. Their spread is the matcher's noise."""
    v, u = np.nonzero(depth.valid)
    z = depth.depth_m[v, u].astype(np.float64)
    k = depth.intrinsics
    ray = np.stack([(u - k.cx_px) / k.fx_px, (v - k.cy_px) / k.fy_px, np.ones_like(z)], 1)
    ray_world = (ray @ depth.rect_from_left) @ pose.R  # rectified -> sensor -> world
    centre = pose.centre_m
    on = np.abs(centre[2] + ray_world[:, 2] * z) < band_m
    true_z = -centre[2] / ray_world[on, 2]  # where the ray meets z = 0
    fb = k.fx_px * depth.baseline_m
    good = true_z > 0
    return fb / z[on][good] - fb / true_z[good]


def make_evidence(args: argparse.Namespace, times_s: list[float]) -> list[Path]:
    folder = Path(args.evidence)
    folder.mkdir(parents=True, exist_ok=True)
    calib = str(Path(args.session).parent / "calibration.toml")
    paths = [folder / f"t{t:09.3f}.npz" for t in times_s]
    jobs = [(args.session, calib, args.config or "", t, str(p))
            for t, p in zip(times_s, paths, strict=True) if not p.is_file()]  # fmt: skip
    if jobs:
        print(f"evidence: {len(jobs)} timestamps to make, {args.workers} workers", flush=True)
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(args.workers) as pool:
            for k, done in enumerate(pool.imap_unordered(_evidence_one, jobs), 1):
                print(f"  {k}/{len(jobs)} {Path(done).name}", flush=True)
    return paths


def sights(paths: list[Path]):
    """Each timestamp's whole evidence with its cameras (``sterile_seen.Sight``), read one at
    a time (a timestamp holds ~400 000 cells); evidence made before the masks: an error."""
    from reconstructor.replay.sterile_seen import Sight

    for p in paths:
        with np.load(p) as z:
            if "seen_by" not in z:
                raise SystemExit(f"{p} has no camera masks: make the evidence again")
            yield Sight(z["points_m"], z["m_per_px"], z["seen_by"], z["camera_centres_m"])


def load_fields(args: argparse.Namespace, paths: list[Path]) -> list[tuple]:
    """Per field box: (box, [(t, name, points in its region, their m_per_px)]), read once."""
    from protocol.formats.site import read_site
    from reconstructor.replay.sterile import Region, SterileConfig

    out = []
    for box in read_site(args.field).values():
        reg = Region(box, SterileConfig())
        stamps = []
        for p in paths:
            with np.load(p) as z:
                pts, noise, t = z["points_m"], z["m_per_px"], float(z["t_s"])
            near = reg.holds(pts)
            stamps.append((t, p.stem, pts[near], noise[near]))
        out.append((box, stamps))
    return out


_FREE: dict[tuple, object] = {}  # freespace per (field, voxel, reach, seen margin)


def judge(fields: list[tuple], roles_path: str, variant: dict, paths: list[Path]) -> list[dict]:
    """The contact events of one detector setting, as rows like ``events.csv``'s, each with
    its peak part's share of in-box points in air and seen through now (``seen``, ``now``)."""
    from reconstructor.replay.sterile import Region, SterileConfig, judge_field
    from reconstructor.replay.sterile_run import _eyes, read_roles
    from reconstructor.replay.sterile_seen import freespace

    cfg = SterileConfig(sterile_roles=STERILE, **variant)
    roles = read_roles(roles_path, STERILE)
    rows: list[dict] = []
    for box, stamps in fields:
        reg = Region(box, cfg)  # the same region as load_fields' unless reach_m changed
        frames = [pts[reg.holds(pts)] for _, _, pts, _ in stamps]
        margins = [cfg.margin_m(nz[reg.holds(pts)]) if cfg.margin_sigmas > 0 else None
                   for _, _, pts, nz in stamps]  # fmt: skip
        eyes = [_eyes(roles, t) for t, _, _, _ in stamps]
        times = [t for t, _, _, _ in stamps]
        key = (box.name, cfg.voxel_m, cfg.reach_m, cfg.seen_margin_sigmas)
        if key not in _FREE:  # ~0.3 s a timestamp: once per setting that changes it
            _FREE[key] = freespace(reg, sights(paths), times)
        free = _FREE[key]
        _, events = judge_field(reg, frames, margins, [(t, n) for t, n, _, _ in stamps], eyes,
                                free)  # fmt: skip
        for e in events:
            kind = "sterile-role" if e.sterile_role else "contact"
            b, t = e.blobs[e.peak], e.instants[e.peak].t_s
            vox = reg.voxels(b.points_m[b.in_field])
            share = free.seen_empty(vox, t, cfg.seen_window_s)
            seen = float("nan") if share is None else float((share >= cfg.air_seen_empty).mean())
            rows.append({"kind": kind, "role": e.role, "start_s": f"{e.start_s:.3f}",
                         "end_s": f"{e.end_s:.3f}", "peak": b.count,
                         "out": len(b.points_m) - b.count, "seen": f"{seen:.2f}",
                         "now": f"{free.now(vox, t).mean():.2f}"})  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("session")
    p.add_argument("--config", help="the reconstruct config TOML (default: the defaults)")
    p.add_argument("--every", type=float, default=0.25)
    p.add_argument("--from", dest="t_from", type=float, required=True)
    p.add_argument("--to", dest="t_to", type=float, required=True)
    p.add_argument("--evidence", required=True, help="folder keeping each timestamp's evidence")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--roles", required=True)
    p.add_argument("--field", required=True)
    p.add_argument("--truth", required=True)
    p.add_argument("--label", default="")
    p.add_argument("--variant", action="append", default=[], help="SterileConfig kwargs")
    p.add_argument("--show-events", action="store_true", help="list each row's contact events")
    p.add_argument("--events-out", type=Path,
                   help="write the defaults row's events (PATH) and its span (PATH with "
                   "_instants.csv) for bench_sterile.py --plot")  # fmt: skip
    args = p.parse_args(argv)
    n = round((args.t_to - args.t_from) / args.every) + 1
    times = [round(args.t_from + k * args.every, 6) for k in range(n)]
    paths = make_evidence(args, times)
    errs = []
    for path in paths:
        with np.load(path) as z:
            if "floor_err_px" in z:
                errs.append(z["floor_err_px"])
    if errs:
        e = np.concatenate(errs)
        mad = 1.4826 * np.median(np.abs(e - np.median(e)))
        print(f"disparity error on the floor: median {np.median(e):+.3f} px, robust sigma "
              f"{mad:.3f} px ({len(e)} pixels sampled)")  # fmt: skip
    truth = [(r["person"], float(r["start_s"]), float(r["end_s"]))
             for r in csv.DictReader(open(args.truth))]  # fmt: skip
    print(f"\n| {args.label or args.session}, {times[0]:g}-{times[-1]:g} s every {args.every:g} s "
          "| recall | false events | per 10 min | start error (s) |")  # fmt: skip
    print("|---|---|---|---|---|")
    fields = load_fields(args, paths)
    for text in ["", *args.variant]:
        variant = eval(f"dict({text})", {"None": None})  # the bench's own flags
        events = judge(fields, args.roles, variant, paths)
        s = score(events, truth, set(STERILE), times[0], times[-1], 0.5, "radiographer")
        errs = ", ".join(f"{e:.2f}" for e in s.start_errors_s)
        print(f"| {text or 'defaults'} | {s.found}/{s.touches} | {s.false_events} | "
              f"{s.false_per_10_min:.0f} | {errs} |", flush=True)  # fmt: skip
        if args.events_out and not text:
            with args.events_out.open("w", newline="") as fh:
                w = csv.DictWriter(fh, ["kind", "role", "start_s", "end_s", "peak", "out",
                                        "seen", "now"])  # fmt: skip
                w.writeheader()
                w.writerows(events)
            span = args.events_out.with_name(args.events_out.stem + "_instants.csv")
            span.write_text("t_s\n" + "".join(f"{t:.3f}\n" for t in times))
        if args.show_events:
            for e in events:
                if e["kind"] == "contact":
                    print(f"    {e['role']} {e['start_s']}-{e['end_s']} peak {e['peak']} "
                          f"in the box, {e['out']} out, in air {e['seen']} seen through now "
                          f"{e['now']}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
