"""``egosurg demo``: the whole chain on the simulated rig, stage by stage.

Example::

    egosurg demo --out out/demo

Stages so far:
1. build the simulated OR and write the rig's eight views, a top-down map and a ground-truth video;
2. run the capture chain as deployed: two simulated Jetson agents (two ZED X each) and the
   recorder as separate processes over loopback TCP; record about 12 s of the OR, sealed for the
   demo's site key, stop, and print the session summary (``egosurg session info``, which opens it
   with the site identity; every later stage's reader does too, through ``EGOSURG_IDENTITY``);
3. calibrate the rig: record a wand session through the same agents and recorder, run
   ``egosurg calibrate`` on it, and compare the recovered camera poses with the sim's truth;
4. reconstruct one timestamp of the stage-2 session with that calibration (``egosurg
   reconstruct``), score it on the recorded views, and render what one of the people saw
   (``egosurg render``) beside the simulator's ground-truth view from the same eyes;
5. evaluate that timestamp as the paper does (``egosurg evaluate``): stage 2's session, the
   calibration and every person's true egocentric view at that instant become an evaluation set
   (``protocol/formats/eval_set.py``), and the table compares depth reprojection, EgoSurg without
   refinement and EgoSurg against those views;
6. batch-reconstruct three consecutive timestamps from there as a case (``egosurg reconstruct
   --every ... --warm-start``, a short schedule) and print its summary (``egosurg case info``).
7. review the case with the roles a real case has: the people found in stage 2's session
   (``egosurg people``, once a second), their tracks named (``egosurg people name``; the demo
   names them by the sim's truth, and says so), then the surgeon's view replayed (``egosurg
   replay --pip``) and the anaesthetist's line of sight to a monitor (``egosurg sightline``);
8. the case report (``egosurg report``, docs/report.md): the drape's sterile field judged
   (``egosurg sterile``) and everything in one HTML file.

Each stage runs through the ``egosurg`` command as a user would run it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Pose
from protocol.command import command_parser
from protocol.formats.eval_set import EvalScene, EvalSet, ReferenceView
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.wand import WandSpec
from protocol.sealing import IDENTITY_ENV
from protocol.session import SessionReader
from sim import pictures
from sim.cli import write_pictures
from sim.demo_names import TrueEyes
from sim.deploy import SimRig, SimRigFiles, SimRigSpec, write_sim_rig
from sim.timing import ClockSpec, content_time_s
from sim.truth import align_to_truth, calibration_errors, true_rig_calibration
from sim.world import World

STAGES = 8


def _stage(k: int, text: str) -> None:
    print(f"[{k}/{STAGES}] {text}", flush=True)


def stage_sim(out: Path, seed: int) -> None:
    _stage(1, "simulated OR: building the room, the rig and the people")
    world = World.from_seed(seed, phase="intraoperative")
    for u in world.rig:
        print(f"      camera SN{u.serial} on {u.node_id}")
    print(f"      people: {', '.join(s.name for s in world.people(0.0))}")
    paths = write_pictures(world, out / "sim", t_s=4.0, video_s=3.0, pictures=pictures)
    print("      wrote:")
    for p in paths:
        print(f"        {p}")


def stage_capture(out: Path, seed: int, record_s: float) -> tuple[Path, SimRigFiles]:
    _stage(2, "capture: 2 agents + recorder as processes on loopback, recording the OR")
    files = write_sim_rig(
        out / "capture",
        SimRigSpec(seed=seed, fps=15.0, content_fps=1.0, prerender_s=record_s + 2.0),
    )
    print(
        f"      the cameras run at {files.spec.fps:.0f} fps; the sim renders the people's motion "
        f"{files.spec.content_fps:.0f} time(s) a second (rendering every frame would take a CPU "
        "minutes), so frames within one second show the same picture"
    )
    for node, path in files.node_configs.items():
        print(f"      egosurg agent --config {path}        ({node})")
    print(f"      egosurg recorder --config {files.rig_config}")
    summary = _record(files, "demo-case", record_s, meta={"procedure": "simulated"})
    session = Path(summary["file"])
    print(
        f"      sealed for the site key {files.keys_dir / 'sim-site.recipient'}; readers open it "
        f"with {IDENTITY_ENV}={files.identity}"
    )
    _egosurg("session", "info", str(session), env=files.reader_env())
    print(f"      logs: {files.directory / 'logs'}")
    return session, files


def _record(files, case: str, record_s: float, meta: dict[str, str] | None = None) -> dict:
    """Start the sim rig's processes, record ``record_s`` seconds with progress, stop."""
    with SimRig(files) as rig:
        t0 = time.monotonic()
        rig.wait_streaming(timeout_s=900)
        print(f"      all 4 cameras streaming after {time.monotonic() - t0:.0f} s")
        started = rig.control("start", case=case, meta=meta or {})
        print(f"      egosurg record start --case {case}   -> {started['file']}")
        for k in range(int(record_s)):
            time.sleep(1.0)
            st = rig.control("status")
            print(
                f"\r      recording: {k + 1:>2}/{int(record_s)} s, {st['sets']} sets, "
                f"{st['bytes'] / 1e6:.0f} MB",
                end="",
                flush=True,
            )
        print()
        summary = rig.control("stop")
        print("      egosurg record stop")
    return dict(summary)


def _egosurg(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """``egosurg *args`` in ``env`` (default: this process's, which names stage 2's identity)."""
    print("      egosurg " + " ".join(args))
    done = subprocess.run(
        [sys.executable, "-m", "protocol.cli", *args],
        capture_output=True,
        text=True,
        check=False,
        env=env,
    )
    print("\n".join("        " + line for line in done.stdout.splitlines()))
    if done.returncode != 0:
        print(done.stderr, file=sys.stderr)
    return done


def stage_calibration(out: Path, seed: int, record_s: float) -> Path | None:
    _stage(3, "calibration: record a wand session, calibrate, compare with the sim's true rig")
    # HD1200: at SVGA the 40 mm spheres are 2 px in radius at 3.5 m, too small to find
    files = write_sim_rig(
        out / "wand",
        SimRigSpec(
            seed=seed,
            phase="wand",
            resolution="HD1200",
            # 10 fps, not 15: every frame is rendered at its own exposure time, and for the
            # calibration the wand's path counts more than the samples along it (the
            # calibration test measured both)
            fps=10.0,
            content_fps=10.0,
            # content loops every N s with the wand on the floor for its first 2 s: record
            # more than N + 2 s so that the floor placement is in the session whole. With the
            # default 36 s, N = 33: the floor, the pick-up and the operator's tour through every
            # camera's view (seed 0's loop: 20 s after the pick-up) and half of it again; with
            # 24 s one camera had 93 usable frames and 8 image regions, short of the report's
            # 100 and 9
            prerender_s=max(record_s - 3.0, 6.0),
            jpeg_quality=92,
        ),
    )
    print(f"      rendering {record_s:.0f} s of an operator waving the wand (takes a while)")
    summary = _record(files, "wand-calibration", record_s)
    session = Path(summary["file"])
    wand = out / "wand" / "wand.toml"
    wand.write_text(WandSpec().to_toml())
    calibration = out / "calibration.toml"
    # the report's own thresholds, as for a real session: the operator's tour takes the wand
    # through every camera's view (sim/wand_tour.py), so the default 36 s pass them
    done = _egosurg(
        "calibrate", str(session), "--wand", str(wand), "--out", str(calibration),
        env=files.reader_env(),  # the wand rig's own site key
    )  # fmt: skip
    if done.returncode != 0 or not calibration.exists():
        print("      calibration failed; see the message above")
        return None
    truth = true_rig_calibration(World.from_seed(seed, phase="wand"), "HD1200")
    print("      against the simulator's true rig (after the best rigid fit of the whole rig):")
    for e in calibration_errors(RigCalibration.read(calibration), truth):
        print(
            f"        {e.name:<20} rotation {e.rotation_deg:.3f} deg, "
            f"position {e.translation_mm:.1f} mm, height {e.height_mm:+.1f} mm"
        )
    print(f"      report: {calibration.parent / 'calibration_report' / 'report.html'}")
    return calibration


@dataclass(frozen=True)
class DemoTimestamp:
    """What stage 4 reconstructed, for stage 5."""

    session: Path
    calibration: Path
    config: Path
    set_index: int
    t_content_s: float


def room_bounds_m(world: World) -> tuple[float, ...]:
    room = world.config.room
    (x0, x1), (y0, y1) = room.x_range_m, room.y_range_m
    return (x0, y0, 0.0, x1, y1, room.height_z_m)


def stage_reconstruction(
    out: Path, seed: int, session: Path, files: SimRigFiles, calibration: Path | None, steps: int
) -> DemoTimestamp | None:
    _stage(4, "reconstruction: Gaussian splats of one timestamp, and a person's view of it")
    world = World.from_seed(seed, phase=files.spec.phase)
    truth = true_rig_calibration(world)
    recon = out / "recon"
    recon.mkdir(parents=True, exist_ok=True)
    cal_path = recon / "calibration.toml"
    if calibration is not None:
        # the wand calibration picks its own heading; move it rigidly into the sim's frame so
        # that the sim's ground-truth views line up with the reconstruction
        align_to_truth(RigCalibration.read(calibration), truth).write(cal_path)
        print("      calibration: stage 3's wand calibration, placed in the sim's world frame")
    else:
        truth.write(cal_path)
        print("      calibration: the sim's true rig (stage 3 did not produce one)")
    # a set in the middle of a second of content, so that every camera shows the same instant
    spec = files.spec
    with SessionReader(session) as reader:
        set_ns = reader.sets().set_unix_ns
    t_exposure = (set_ns - files.epoch_unix_ns) / 1e9 - ClockSpec().readout_latency_ns / 1e9
    middle = np.abs((t_exposure * spec.content_fps) % 1.0 - 0.5)
    middle[: len(middle) // 3] = np.inf
    k = int(np.argmin(middle))
    # the room's box, as a site measures it once: blank walls no stereo matcher can match are
    # seen through to it (reconstructor/depth/fill.py)
    config = recon / "site.toml"
    config.write_text(f"room_bounds_m = {list(room_bounds_m(world))}\n")
    done = _egosurg(
        "reconstruct", str(session), "--calibration", str(cal_path), "--at", f"set:{k}",
        "--out", str(recon), "--steps", str(steps), "--evaluate", "--config", str(config),
    )  # fmt: skip
    runs = sorted(p for p in recon.iterdir() if (p / "splats.ply").exists())
    if done.returncode != 0 or not runs:
        print("      reconstruction failed; see the message above")
        return None
    model = runs[-1] / "splats.ply"
    t_content = content_time_s(
        float(t_exposure[k]),
        fps=spec.fps,
        content_fps=spec.content_fps,
        prerender_s=spec.prerender_s,
    )
    stamp = DemoTimestamp(session, cal_path, config, k, t_content)
    heads = world.head_poses(t_content)
    who = next((n for n in heads if "surgeon" in n), next(iter(heads)))
    eye = heads[who].centre_m
    target = eye + heads[who].R[2]  # the head camera's forward axis
    view = Pose.look_at(eye, target)
    cam = world.virtual_camera(view, hfov_deg=90.0, size_px=(960, 600), name=f"{who}'s eyes")
    rendered_png = recon / f"{who}_view_splats.png"
    eye_s, target_s = ",".join(f"{v:.4f}" for v in eye), ",".join(f"{v:.4f}" for v in target)
    # --near-m 0.2: from a person's eye, leave out their own head (as the egocentric protocol)
    done = _egosurg(
        "render", str(model), "--camera", f"eye={eye_s} target={target_s}",
        "--hfov", "90", "--size", "960x600", "--near-m", "0.2", "--out", str(rendered_png),
    )  # fmt: skip
    if done.returncode != 0:
        return stamp
    truth_rgb = world.render(cam, t_content).image_rgb
    bgr = cv2.imread(str(rendered_png))
    if bgr is None:
        print(f"      cannot read {rendered_png}")
        return stamp
    rendered = bgr[:, :, ::-1]
    mse = float(np.mean((rendered.astype(np.float64) - truth_rgb.astype(np.float64)) ** 2))
    psnr_db = 10 * np.log10(255.0**2 / max(mse, 1e-9))
    pair = np.concatenate([truth_rgb, rendered], axis=1)[:, :, ::-1].copy()
    for x, label in ((10, f"ground truth: {who}'s eyes"), (970, f"splats ({steps} steps)")):
        cv2.putText(pair, label, (x, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 3)
        cv2.putText(pair, label, (x, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 1)
    side = recon / f"{who}_view_vs_truth.png"
    cv2.imwrite(str(side), pair)
    print(f"      {who}'s view, rendered vs the sim's ground truth: PSNR {psnr_db:.1f} dB")
    print(f"      wrote {side}")
    return stamp


def stage_evaluation(out: Path, seed: int, phase: str, stamp: DemoTimestamp, steps: int) -> None:
    _stage(5, "evaluation: the paper's egocentric protocol on that timestamp")
    world = World.from_seed(seed, phase=phase)
    root = out / "evalset"
    (root / "views").mkdir(parents=True, exist_ok=True)
    views = []
    for role, pose in world.head_poses(stamp.t_content_s).items():
        name = f"{role}@{stamp.set_index}"
        cam = world.virtual_camera(pose, hfov_deg=90.0, size_px=(960, 600), name=name)
        image = world.render(cam, stamp.t_content_s).image_rgb
        cv2.imwrite(str(root / "views" / f"{name}.png"), image[:, :, ::-1].copy())
        views.append(
            ReferenceView(
                name=name,
                kind="egocentric",
                role=role,
                set_index=stamp.set_index,
                image=f"views/{name}.png",
                camera=cam,
            )
        )
    scene = EvalScene(
        name="demo",
        phase=phase,
        session=str(stamp.session.resolve()),
        calibration=str(stamp.calibration.resolve()),
        eval_sets=(stamp.set_index,),
        temporal_sets=(),
        views=tuple(views),
        room_bounds_m=room_bounds_m(world),
    )
    manifest = EvalSet(
        root=root,
        description=f"stage 2's session at set {stamp.set_index}, with the sim's egocentric views",
        scenes=(scene,),
    ).write()
    print(f"      evaluation set: {manifest} ({len(views)} people's views)")
    # a rerun of the demo evaluates its new recording afresh (egosurg evaluate keeps an earlier
    # run's finished jobs unless told --resume, and refuses to overwrite them)
    shutil.rmtree(out / "evaluation", ignore_errors=True)
    done = _egosurg(
        "evaluate", str(root), "--out", str(out / "evaluation"), "--protocol", "egocentric",
        "--methods", "depth-reprojection", "no-refinement", "egosurg",
        "--steps", str(steps), "--train-width", "480",
    )  # fmt: skip
    if done.returncode != 0:
        print("      evaluation failed; see the message above")


def stage_batch(out: Path, stamp: DemoTimestamp, steps: int, content_fps: float) -> None:
    _stage(6, "batch: three consecutive timestamps as a case, warm-started, then its summary")
    with SessionReader(stamp.session) as reader:
        started = reader.info.started_unix_ns
        set_ns = reader.sets().set_unix_ns
    first_s, last_s = (int(set_ns[0]) - started) / 1e9, (int(set_ns[-1]) - started) / 1e9
    # one second apart, as the sim renders the people's motion (stage 2): three timestamps
    # closer together would be three reconstructions of the same picture
    every_s = 1.0 / content_fps
    if last_s - first_s < 2 * every_s + 0.1:
        every_s = max((last_s - first_s - 0.1) / 2, 0.05)
        print(f"      the recording is short: timestamps {every_s:.2f} s apart (the same picture)")
    t_s = (int(set_ns[stamp.set_index]) - started) / 1e9
    t_s = max(min(t_s, last_s - 2 * every_s - 0.05), first_s)
    case = out / "case"
    done = _egosurg(
        "reconstruct", str(stamp.session), "--calibration", str(stamp.calibration),
        "--config", str(stamp.config), "--every", f"{every_s:.3f}s", "--from", f"{t_s:.3f}",
        "--to", f"{t_s + 2 * every_s:.3f}", "--out", str(case),
        "--steps", str(max(steps // 4, 1)),
        "--train-views", "left", "--no-refinement", "--warm-start",
        "--warm-steps", str(max(steps // 32, 1)),
    )  # fmt: skip
    if done.returncode != 0:
        print("      batch reconstruction failed; see the message above")
        return
    _egosurg("case", "info", str(case))


def stage_review(out: Path, seed: int, files: SimRigFiles, stamp: DemoTimestamp) -> None:
    """The paper's case studies as tools, on the case of stage 6, with the roles a real case has:
    the people found in the recording (``egosurg people`` on the session, once a second: the
    sim's people move once a second), their tracks named (here by the sim's truth, for the demo
    only), then one named person's view replayed over the case with the nearest real camera
    inset, and whether the anaesthetist could see a monitor from where they stood, and from a
    metre to their left and back."""
    from protocol.formats.site import site_toml
    from sim.roles import site_boxes
    from sim.timing import read_session_clock

    _stage(7, "review: find the people, name their tracks, replay a view, test a line of sight")
    case, review = out / "case", out / "review"
    review.mkdir(parents=True, exist_ok=True)
    site, people, roles = review / "site.toml", review / "people.toml", review / "roles.toml"
    world = World.from_seed(seed, phase=files.spec.phase)
    # the monitors, as a site measures them once, made for this session
    site.write_text(site_toml(site_boxes(world), session=read_session_clock(stamp.session).session))
    print(f"      the site's monitors: {site}")
    with SessionReader(stamp.session) as reader:
        started = reader.info.started_unix_ns
        set_ns = reader.sets().set_unix_ns
    first_s = (int(set_ns[0]) - started) / 1e9
    t_mid = (int(set_ns[stamp.set_index]) - started) / 1e9
    # once a second, in the middle of each second of the sim's content, as stage 4's timestamp:
    # faster would show each picture again, and at a change of picture the cameras differ
    t_from = first_s + (t_mid - first_s) % 1.0
    print("      the people, found in the recording itself (no simulator on this path):")
    done = _egosurg(
        "people", str(stamp.session), "--calibration", str(stamp.calibration), "--every", "1",
        "--from", f"{t_from:.3f}", "--out", str(people),
    )  # fmt: skip
    if done.returncode != 0 or not people.is_file():
        print("      no people found (see the message above; here 'egosurg people' needs 10 s or")
        print("      more of the room: --record-s 12): no roles to review with")
        return
    spec, latency_s = files.spec, ClockSpec().readout_latency_ns / 1e9

    def true_eyes(t_case_s: float) -> dict[str, np.ndarray]:
        """The sim's eyes in the picture the cameras showed at case time ``t_case_s``."""
        t_exposure = (started - files.epoch_unix_ns) / 1e9 + t_case_s - latency_s
        t = content_time_s(t_exposure, fps=spec.fps, content_fps=spec.content_fps,
                           prerender_s=spec.prerender_s)  # fmt: skip
        return {name: pose.centre_m for name, pose in world.head_poses(t).items()}

    found = _name_tracks(people, true_eyes, world.head_poses(0.0), roles)
    if found is None:
        return
    replay_role, viewer = found
    done = _egosurg(
        "replay", str(case), "--role", replay_role, "--roles", str(roles),
        "--out", str(review / f"{replay_role}.mp4"), "--size", "480x300", "--pip",
    )  # fmt: skip
    if done.returncode != 0:
        print("      replay failed; see the message above")
    done = _egosurg(
        "sightline", str(case), "--viewer", viewer, "--roles", str(roles),
        "--target", "monitor-a", "--site", str(site), "--offset", "1m left-posterior",
        "--out", str(review / "sightline"),
    )  # fmt: skip
    if done.returncode != 0:
        print("      line of sight failed; see the message above")


def _name_tracks(
    people: Path, true_eyes: TrueEyes, everyone: dict[str, Pose], roles: Path
) -> tuple[str, str] | None:
    """Stage 7's naming: the tracks named after the sim's people, written by ``egosurg people
    name``; the roles to replay and to test the line of sight of (None: nobody to review)."""
    import json

    from sim.demo_names import MAX_NAMING_M, covering, name_by_truth

    named = name_by_truth(people, true_eyes)
    print(
        "      naming the tracks: on a real case you do it ('egosurg people name "
        f"{people} --list --suggest', or click them in 'egosurg view --people'); the demo "
        f"names them by the SIMULATOR'S TRUTH, for the demo only: each track after the person "
        f"whose true eye is nearest it (median over its keyframes, within {MAX_NAMING_M} m):"
    )
    for n in named:
        print(f"        {n.track} = {n.role} ({n.median_m:.2f} m from the true eye)")
    unfound = [r for r in everyone if r not in {n.role for n in named}]
    if unfound:
        print(
            f"      no track within {MAX_NAMING_M} m of: {', '.join(unfound)} (someone who stands "
            "still through the whole recording is taken for part of the room, a head hidden "
            "by others is missed: docs/replay.md, 'Limits')"
        )
    if not named:
        print("      no track is within reach of a person: nothing to review")
        return None
    done = _egosurg(
        "people", "name", str(people), *(f"{n.track}={n.role}" for n in named),
        "--out", str(roles),
    )  # fmt: skip
    if done.returncode != 0:
        return None
    index = json.loads((people.parent.parent / "case" / "case.json").read_text())
    times = [float(e["t_s"]) for e in index["timestamps"] if e.get("status") == "done"]
    through = covering(named, people, times)
    if not through:
        print("      no named track spans two of the case's timestamps: nothing to replay")
        return None
    pick = "surgeon" if "surgeon" in through else through[0]
    viewer = "anaesthetist" if "anaesthetist" in through else through[0]
    if {pick, viewer} != {"surgeon", "anaesthetist"}:
        print(f"      the replay follows the {pick}, the line of sight the {viewer}: named "
              "tracks over the case's timestamps")  # fmt: skip
    return pick, viewer


def stage_report(out: Path) -> None:
    """The case report of stage 6's case: the session's health, the timeline with the sterile
    field (the drape) and stage 7's line of sight, each role's view beside the nearest real
    camera, one HTML file (docs/report.md)."""
    import json

    from protocol.formats.site import site_toml
    from protocol.formats.trajectory import read_trajectories
    from sim.contact import DRAPE_FIELD
    from sim.timing import read_session_clock

    _stage(8, "report: the case in one HTML file (health, timeline, events, views)")
    case, review = out / "case", out / "review"
    review.mkdir(parents=True, exist_ok=True)
    session = Path(json.loads((case / "case.json").read_text())["session"])
    field = review / "field.toml"  # the drape, made for this session
    field.write_text(site_toml([DRAPE_FIELD], session=read_session_clock(session).session))
    roles = review / "roles.toml"
    with_roles: tuple[str, ...] = ()
    sterile_roles: tuple[str, ...] = ()
    if roles.is_file():
        # the gowned team, those of them the roles file has (stage 7 names the tracks it found)
        named = {t.name for t in read_trajectories(roles)}
        gowned = [r for r in ("surgeon", "assistant", "nurse_scrub") if r in named]
        with_roles = ("--roles", str(roles))
        sterile_roles = ("--sterile-roles", ",".join(gowned))
    else:
        print("      no roles from stage 7: contacts are given to no one, and no role's view")
    done = _egosurg(
        "sterile", str(case), "--field", str(field), *with_roles, *sterile_roles,
        "--out", str(review / "sterile"),
    )  # fmt: skip
    sterile = ("--sterile", str(review / "sterile")) if done.returncode == 0 else ()
    sightline = review / "sightline"
    sight = ("--sightline", str(sightline)) if (sightline / "sightline.csv").is_file() else ()
    done = _egosurg(
        "report", str(case), *with_roles, *sterile, *sight, "--out", str(review / "report.html"),
    )  # fmt: skip
    if done.returncode != 0:
        print("      the report failed; see the message above")


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg demo", __doc__)
    parser.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument(
        "--record-s",
        type=float,
        default=12.0,
        help="length of the recording (10 s or more for stage 7 to find the people in it)",
    )
    parser.add_argument(
        "--wand-s", type=float, default=36.0, help="length of the wand recording (stage 3)"
    )
    parser.add_argument(
        "--steps", type=int, default=200, help="training steps of stage 4 (the paper: 2000)"
    )
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    stage_sim(out, args.seed)
    session, files = stage_capture(out, args.seed, args.record_s)
    # stages 4-7 read stage 2's sealed session as a reading workstation does, with the site
    # identity in the environment (SimRig keeps it from the rig's own processes)
    os.environ[IDENTITY_ENV] = str(files.identity)
    calibration = stage_calibration(out, args.seed, args.wand_s)
    stamp = stage_reconstruction(out, args.seed, session, files, calibration, args.steps)
    if stamp is not None:
        stage_evaluation(out, args.seed, files.spec.phase, stamp, args.steps)
        stage_batch(out, stamp, args.steps, files.spec.content_fps)
        stage_review(out, args.seed, files, stamp)
        stage_report(out)
    print(f"demo finished in {time.perf_counter() - t0:.0f} s; everything is under {out}/")
    return 0
