"""``egosurg people`` against the simulator's truth: for each phase, people found in the
recording, tracked and given head poses, compared with ``World.head_poses``.

Per phase and per person: eye position error (median, p95), yaw and pitch error (median),
the share of person-seconds tracked among those in which the person is seen by at least two
cameras (a ray from the camera to the head's centre reaches the head), identity switches per 10
minutes, and seconds per timestamp (reading the points: stereo for a session; finding people).
The judge is CLEAR MOT's (Bernardin & Stiefelhagen, "Evaluating Multiple Object Tracking
Performance: The CLEAR MOT Metrics", EURASIP J. Image and Video Processing, 2008, section 2.1):
at each timestamp a truth person keeps the track they were matched to at the previous timestamp
while that track is still within 0.5 m of them; the others are matched to the tracks left by
least total distance within 0.5 m (``scipy.optimize.linear_sum_assignment``); an identity switch
(a mismatch) is a person matched to another track than the last one they were matched to. The
judge before it, with no keeping step (every timestamp matched afresh by least total distance), is
reported beside it ("nearest"): a second track beside a person that is sometimes nearer makes it
count switches the standard procedure does not.

Examples::

    .venv/bin/python bench/bench_people.py --phases intraoperative --seconds 20 --hz 2
    .venv/bin/python bench/bench_people.py --cases intraoperative=/tmp/case_intra --seconds 60

Sessions are written (``egosurg sim eval-set`` at ``--hz`` fps) under ``--work`` and kept.
``--cases PHASE=CASE,...``: reconstructed cases of those sessions (``egosurg reconstruct
SESSION --every 0.5s ...``), each judged through both routes on the same timestamps: the
evidence the case stores (its cells, with the cameras that saw them) and its session's stereo
(the session's cached points, made again and timed on ``--stereo-timed`` of them).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

MATCH_M = 0.5


@dataclass
class Scores:
    """Per-person lists over matched timestamps, and the counts for shares and switches."""

    pos_err_m: list[float]
    yaw_err_deg: list[float]
    pitch_err_deg: list[float]
    visible: int = 0  # timestamps seen by >= 2 cameras
    tracked_visible: int = 0
    switches: int = 0  # CLEAR MOT's mismatches
    switches_nearest: int = 0  # the same matched afresh at each timestamp, no keeping step
    seconds: float = 0.0


def truth_angles(pose) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """(yaw, pitch) radians of a world-to-camera pose's optical axis (pitch positive down)."""
    f = pose.R[2]
    return math.atan2(f[1], f[0]), -math.asin(float(np.clip(f[2], -1, 1)))


def angle_deg(a: float, b: float) -> float:
    return abs(math.degrees((a - b + math.pi) % (2 * math.pi) - math.pi))


def cameras_seeing(world, t_s: float, head_m: np.ndarray, centres: np.ndarray) -> int:  # type: ignore[no-untyped-def]
    """How many of the cameras (their centres, (C, 3)) see the head: a ray from the camera to the
    head's centre hits nothing closer than 12 cm before it."""
    d = head_m[None, :] - centres
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([centres, d / dist[:, None]], axis=1).astype(np.float32)
    t_hit, _, _ = world.scene_at(t_s).cast_rays(rays)
    return int(np.sum(t_hit >= dist - 0.12))


def correspond(
    truth: dict[str, np.ndarray],
    tracks: list[tuple[int, np.ndarray]],
    previous: dict[str, int],
    match_m: float = MATCH_M,
) -> dict[str, int]:
    """One timestamp of CLEAR MOT's correspondence (Bernardin & Stiefelhagen 2008, section
    2.1.1): {person: index into ``tracks``}. ``truth``: each person's true position; ``tracks``:
    (track id, estimated position); ``previous``: {person: track id} matched at the timestamp
    before. A person keeps their previous track while it is here within ``match_m`` of them;
    the rest are paired by least total distance within ``match_m``. ``previous={}`` at every
    timestamp is the judge without the keeping step."""
    kept: dict[str, int] = {}
    where = {tid: j for j, (tid, _) in enumerate(tracks)}
    for name, tid in previous.items():
        j = where.get(tid)
        if name in truth and j is not None:
            if float(np.linalg.norm(tracks[j][1] - truth[name])) <= match_m:
                kept[name] = j
    names = [n for n in truth if n not in kept]
    free = [j for j in range(len(tracks)) if j not in kept.values()]
    cost = np.full((len(names), len(free)), 1e6)
    for i, n in enumerate(names):
        for k, j in enumerate(free):
            d = float(np.linalg.norm(tracks[j][1] - truth[n]))
            if d <= match_m:
                cost[i, k] = d
    if cost.size:
        for i, k in zip(*linear_sum_assignment(cost), strict=True):
            if cost[i, k] < 1e6:
                kept[names[i]] = free[k]
    return kept


def mismatches(
    frames: list[tuple[dict[str, np.ndarray], list[tuple[int, np.ndarray]]]], keep: bool = True
) -> tuple[list[dict[str, int]], dict[str, int]]:
    """CLEAR MOT over ``frames`` ((truth, tracks) per timestamp, as ``correspond`` takes them):
    each timestamp's {person: track id} and each person's identity switches, a switch being a
    match to another track than the last one they were matched to (however long ago).
    ``keep=False``: the judge without the keeping step."""
    previous: dict[str, int] = {}
    last: dict[str, int] = {}
    switches: dict[str, int] = {}
    out = []
    for truth, tracks in frames:
        match = correspond(truth, tracks, previous if keep else {})
        previous = {n: tracks[j][0] for n, j in match.items()}
        for n, tid in previous.items():
            switches[n] = switches.get(n, 0) + (n in last and last[n] != tid)
            last[n] = tid
        out.append(previous)
    return out, switches


@dataclass(frozen=True)
class Truth:
    """A person at a timestamp, from the world: the head's centre, the gaze's yaw and pitch
    (radians), and whether at least two cameras see the head."""

    centre_m: np.ndarray
    yaw_rad: float
    pitch_rad: float
    seen: bool


def truth_at(world, t_s: float, camera_centres: np.ndarray) -> dict[str, Truth]:  # type: ignore[no-untyped-def]
    states = {s.name: s for s in world.people(t_s)}
    out = {}
    for n, pose in world.head_poses(t_s).items():
        seen = cameras_seeing(world, t_s, states[n].head_centre_m, camera_centres) >= 2
        out[n] = Truth(np.asarray(pose.centre_m), *truth_angles(pose), seen)
    return out


def score(
    world, people, config, camera_centres: np.ndarray, duration_s: float
) -> dict[str, Scores]:  # type: ignore[no-untyped-def]
    """Compare the estimated ``people`` (reconstructor.people.run.People) with the world's truth
    at each of its timestamps (case time = sim time: eval-set sessions start at the sim epoch)."""
    truths = [truth_at(world, t, camera_centres) for t in people.times_s]
    return score_truth(truths, people.times_s, people.poses, duration_s)


def score_truth(
    truths: list[dict[str, Truth]], times_s, poses: dict, duration_s: float
) -> dict[str, Scores]:  # type: ignore[no-untyped-def]
    """``score`` on the truth at each of ``times_s`` (``truth_at``) and each track's head
    poses ({track id: [HeadPose]})."""
    poses_at: dict[float, dict[int, object]] = {}
    for tid, track_poses in poses.items():
        for p in track_poses:
            poses_at.setdefault(round(p.time_s, 6), {})[tid] = p
    frames = []
    for t, truth in zip(times_s, truths, strict=True):
        est = poses_at.get(round(t, 6), {})
        frames.append(({n: tr.centre_m for n, tr in truth.items()},
                       [(tid, p.eye_m) for tid, p in est.items()]))  # type: ignore[attr-defined]  # fmt: skip
    matched, switches = mismatches(frames)
    _, nearest = mismatches(frames, keep=False)
    out: dict[str, Scores] = {}
    for t, truth, match in zip(times_s, truths, matched, strict=True):
        est = poses_at.get(round(t, 6), {})
        for n, tr in truth.items():
            s = out.setdefault(n, Scores([], [], []))
            s.visible += tr.seen
            if n not in match:
                continue
            p = est[match[n]]
            s.tracked_visible += tr.seen
            s.pos_err_m.append(float(np.linalg.norm(p.eye_m - tr.centre_m)))  # type: ignore[attr-defined]
            s.yaw_err_deg.append(angle_deg(p.yaw_rad, tr.yaw_rad))  # type: ignore[attr-defined]
            s.pitch_err_deg.append(abs(math.degrees(p.pitch_rad - tr.pitch_rad)))  # type: ignore[attr-defined]
    for n, s in out.items():
        s.seconds = duration_s
        s.switches = switches.get(n, 0)
        s.switches_nearest = nearest.get(n, 0)
    return out


def row(name: str, s: Scores) -> str:
    def q(v: list[float], k: float, scale: float = 1.0) -> str:
        return f"{np.percentile(v, k) * scale:6.1f}" if v else "     -"

    share = s.tracked_visible / s.visible if s.visible else float("nan")
    per10 = 600 / s.seconds if s.seconds else float("nan")
    return (
        f"| {name:16s} | {q(s.pos_err_m, 50, 100)} | {q(s.pos_err_m, 95, 100)} | "
        f"{q(s.yaw_err_deg, 50)} | {q(s.pitch_err_deg, 50)} | {100 * share:5.1f} | "
        f"{s.switches:3d} ({s.switches * per10:5.1f}) | "
        f"{s.switches_nearest:3d} ({s.switches_nearest * per10:5.1f}) |"
    )


HEADER = (
    "| person           | pos med cm | pos p95 cm | yaw med deg | pitch med deg | tracked % | "
    "switches (per 10 min) | nearest-match switches (per 10 min) |\n"
    "|---|---|---|---|---|---|---|---|"
)


def session_clouds(session: Path, every_s: float) -> tuple[list[np.ndarray], float]:
    """Each timestamp's stereo points of a session (every ``every_s`` s) and the seconds they
    took, made once and kept beside the session (``people_points_every<s>.npz``)."""
    from reconstructor.people.sources import open_source

    source = open_source(session, every_s=every_s)
    cache = session.parent / f"people_points_every{every_s:g}.npz"
    if cache.is_file():  # the stereo points of an earlier run (delete it to make them again)
        z = np.load(cache)
        return [z[f"k{k}"] for k in range(len(source.times_s))], float(z["read_s"])
    t0 = time.perf_counter()
    clouds = [source.points(k) for k in range(len(source.times_s))]
    read_s = time.perf_counter() - t0
    np.savez(cache, read_s=read_s, **{f"k{k}": c for k, c in enumerate(clouds)})
    return clouds, read_s


def run_phase(session: Path, seed: int, phase: str, every_s: float) -> tuple[str, dict]:
    from reconstructor.people.sources import open_source

    source = open_source(session, every_s=every_s)
    clouds, read_s = session_clouds(session, every_s)
    return judge(source, clouds, read_s, seed, phase, session.parent / "calibration.toml", every_s)


def judge(source, clouds, read_s, seed, phase, calibration, every_s, label=""):  # type: ignore[no-untyped-def]
    """``find_people`` on ``clouds`` (one per timestamp of ``source``, made in ``read_s``),
    judged against the world's truth: the report's lines and the numbers."""
    from protocol.formats.rig_calibration import RigCalibration
    from reconstructor.people.config import PeopleConfig
    from reconstructor.people.run import find_people
    from sim.world import World

    config = PeopleConfig()
    source = dataclasses.replace(source, _load=lambda k: clouds[k])
    t0 = time.perf_counter()
    people = find_people(source, config)
    wall = time.perf_counter() - t0 + read_s
    people.seconds["read"] = read_s
    world = World.from_seed(seed, phase=phase)
    rig = RigCalibration.read(calibration)
    centres = np.array([s.camera.pose.centre_m for s in rig.sensors if s.side == "left"])
    duration = source.times_s[-1] - source.times_s[0] + every_s
    scores = score(world, people, config, centres, duration)
    n = len(source.times_s)
    sec = people.seconds
    lines = [f"\n{phase}{label}, seed {seed}: {n} timestamps over {duration:.0f} s, "
             f"{len(people.tracks)} tracks for {len(scores)} people; "
             f"{wall / n:.2f} s per timestamp (reading points {sec['read'] / n:.2f}, "
             f"finding people {(sec['detect'] + sec['background'] + sec['track']) / n:.2f})",
             HEADER]  # fmt: skip
    allsc = Scores([], [], [], seconds=0.0)
    for name, s in scores.items():
        lines.append(row(name, s))
        allsc.pos_err_m += s.pos_err_m
        allsc.yaw_err_deg += s.yaw_err_deg
        allsc.pitch_err_deg += s.pitch_err_deg
        allsc.visible += s.visible
        allsc.tracked_visible += s.tracked_visible
        allsc.switches += s.switches
        allsc.switches_nearest += s.switches_nearest
        allsc.seconds += s.seconds
    lines.append(row("all", allsc))
    return "\n".join(lines), {"scores": scores, "people": people, "all": allsc}


def run_case(  # type: ignore[no-untyped-def]
    case: Path, session: Path, seed: int, phase: str, every_s: float, time_session: int
):
    """The case's timestamps through both routes: its stored evidence (read and checked, timed
    over all of them) and its session's stereo (the session's cached points at the same sets;
    made again and timed on ``time_session`` of them)."""
    from reconstructor.case.index import CaseIndex
    from reconstructor.people.sources import open_source

    stored = open_source(case)
    t0 = time.perf_counter()
    clouds = [stored.points(k) for k in range(len(stored.times_s))]
    read_s = time.perf_counter() - t0
    calibration = case / "calibration.toml"
    yield judge(stored, clouds, read_s, seed, phase, calibration, every_s, " (case evidence)")[0]
    n_pts = [len(c) for c in clouds]
    sets = [e.set_index for e in CaseIndex.read(case).timestamps if e.status == "done"]
    all_sets, _ = session_clouds(session, every_s)  # every set of a 2 Hz session: k = set
    again = open_source(case, stored_first=False)
    assert again.times_s == stored.times_s
    picks = np.linspace(0, len(sets) - 1, time_session).round().astype(int) if time_session else []
    t0 = time.perf_counter()
    for k in picks:
        again.points(int(k))
    per_ts = (time.perf_counter() - t0) / max(len(picks), 1)
    clouds = [all_sets[s] for s in sets]
    text = judge(stored, clouds, per_ts * len(sets), seed, phase, calibration, every_s,
                 f" (session stereo, timed on {len(picks)} timestamps)")[0]  # fmt: skip
    yield text
    yield (f"points per timestamp, median: case evidence (seen twice) {np.median(n_pts):.0f}, "
           f"session stereo (seen twice) {np.median([len(c) for c in clouds]):.0f}")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", default="3", help="comma-separated world seeds (3)")
    ap.add_argument("--phases", default="setup,intraoperative,turnover")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each phase's session")
    ap.add_argument("--hz", type=float, default=2.0, help="timestamps per second")
    ap.add_argument("--work", default="/tmp/bench_people", help="where sessions are written")
    ap.add_argument("--cases", help="PHASE=CASE,...: cases of --work's sessions, both routes")
    ap.add_argument("--stereo-timed", type=int, default=3,
                    help="timestamps whose session stereo is made again and timed (3)")  # fmt: skip
    args = ap.parse_args()
    from sim.eval_set import EvalSetSpec, write_eval_set

    if args.cases:
        for item in args.cases.split(","):
            phase, case = item.split("=", 1)
            seed = int(args.seeds.split(",")[0])
            folder = Path(args.work) / f"seed{seed}-{args.seconds:g}s-{args.hz:g}hz"
            session = folder / phase / "session.h5"
            for text in run_case(Path(case), session, seed, phase, 1 / args.hz, args.stereo_timed):
                print(text, flush=True)
        return 0
    for seed in (int(s) for s in args.seeds.split(",")):
        for phase in args.phases.split(","):
            folder = Path(args.work) / f"seed{seed}-{args.seconds:g}s-{args.hz:g}hz"
            session = folder / phase / "session.h5"
            if not session.is_file():
                sets = round(args.seconds * args.hz)
                spec = EvalSetSpec(seed=seed, phases=(phase,), fps=args.hz, sets=sets,
                                   instants=1, view_size_px=(64, 40))  # fmt: skip
                write_eval_set(folder, spec)
            text, _ = run_phase(session, seed, phase, 1 / args.hz)
            print(text, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
