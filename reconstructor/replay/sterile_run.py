"""``sterile`` over a case: the moving things in each field box over time, the contact events,
and for each event a render from the best unoccluded viewpoint (``reconstructor/replay/sterile.py``
has the method).

**Evidence.** The points judged are each timestamp's fused stereo points, stored with its model
(``case/storage.py``): what the cameras saw then. A trained model is a rendering of them, and
not the same evidence: training moves and prunes Gaussians, and a warm-started timestamp carries
its predecessor's and seeds an arm that reaches in sparsely (where earlier Gaussians' shapes
cover it). On the 7-timestamp contact case of ``test_sterile.py``, the touch was found from
3-step cold models (whose centres are the fused points) and missed from 250-step cold ones and
from warm chains. A case stored without points (PLY models, or made before 2026-11-27) is
judged on its Gaussians' centres (opacity at least ``min_opacity``), as before.

Writes ``events.csv``, ``instants.csv`` (each timestamp: moving points in each field and the
blobs touching it), ``timeline.png``, ``event_<k>.png`` per contact and ``made_for.toml`` (the
case and session: ``session_check.py``); and, from the session's real frames, each contact's
``event_<k>_camera.png`` and ``event_<k>_clip.mp4`` from the rig camera that saw it best
(``sterile_evidence.py``). Without those frames (a sealed session read without its identity,
or the session gone) the rest is written and ``SterileResult.real_note`` says why."""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Camera, Intrinsics, Pose
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.site import SiteBox
from protocol.formats.trajectory import TIME_RESOLUTION_S
from protocol.sealing import Identity, IdentityRequiredError
from reconstructor.case.storage import load_observation
from reconstructor.data.views import EYE_NEAR_M
from reconstructor.errors import CaseReplayError, SightlineError, SterileError
from reconstructor.replay.clock import CaseClock, add_time_of_day_axis, pick_zone
from reconstructor.replay.frame import no_data_legend, show_no_data
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.path import CameraPath
from reconstructor.replay.run import RealCameras, case_raster, render_view
from reconstructor.replay.session_check import MADE_FOR_NAME, CaseInputs, write_made_for
from reconstructor.replay.sightline import visible_fraction
from reconstructor.replay.sightline_pictures import outline_box
from reconstructor.replay.sterile import (
    Event,
    Instant,
    Region,
    SterileConfig,
    judge_field,
    set_aside,
)
from reconstructor.replay.sterile_evidence import CameraEvidence, camera_evidence
from reconstructor.replay.sterile_pictures import event_plan, event_span
from reconstructor.replay.sterile_seen import Sight, freespace
from reconstructor.replay.video import burn_text, timecode

log = logging.getLogger(__name__)
MIN_TIMESTAMPS = 3  # fewer cannot tell the static scene from what moves


@dataclass(frozen=True)
class SterileResult:
    instants: dict[str, list[Instant]]  # per field
    events: list[Event]
    renders: dict[int, tuple[Path, str, float]]  # event number -> (png, viewpoint, unoccluded)
    evidence: str = "points"  # "points": the stored fused points; "gaussians": model centres
    cameras: dict[int, CameraEvidence] = field(default_factory=dict)  # event -> real camera's
    real_note: str = ""  # why there is no real-camera evidence ("" when there is, or no contact)
    set_aside: list[Event] = field(default_factory=list)  # contacts test 6 set aside (listed)

    @property
    def contacts(self) -> list[Event]:
        return [e for e in self.events if not e.sterile_role]

    def files(self, out: Path) -> list[Path]:
        """Every file the run wrote in ``out``."""
        names = ("events.csv", "set_aside.csv", "instants.csv", "timeline.png", MADE_FOR_NAME)
        named = [out / n for n in names]
        named += [png for png, _, _ in self.renders.values()]
        named += [p for c in self.cameras.values() for p in (c.still, c.clip) if p is not None]
        return [p for p in named if p.is_file()]


def _eyes(paths: list[CameraPath], t_s: float) -> dict[str, np.ndarray | None]:
    """Each role's eye at ``t_s``; None where the role was not followed then (inside a gap of
    its track, or outside its keyframes): a path's eye there is a guess, no one's
    (``sterile.NOT_FOLLOWED``)."""
    return {p.name: _eye(p, t_s) for p in paths}


def _eye(path: CameraPath, t_s: float) -> np.ndarray | None:
    t0, t1 = path.span_s
    if path.gap_at(t_s) is not None or not t0 - TIME_RESOLUTION_S <= t_s <= t1 + TIME_RESOLUTION_S:
        return None
    return path.pose(float(np.clip(t_s, t0, t1))).centre_m


def sterile(
    folder: Path, boxes: list[SiteBox], paths: list[CameraPath], out: Path,
    config: SterileConfig | None = None, *, t_from_s: float | None = None,
    t_to_s: float | None = None, allow_gaps: bool = False, progress=None, device: str = "cpu",
    identity: Identity | None = None, timezone: str | None = None,
) -> SterileResult:  # fmt: skip
    config = config or SterileConfig()
    models = CaseModels(folder, identity)  # a sealed session's case opens with it
    c0, c1 = models.span_s
    t0 = c0 if t_from_s is None else t_from_s
    t1 = c1 if t_to_s is None else t_to_s
    entries = [e for e in models.entries if t0 - 1e-6 <= e.t_s <= t1 + 1e-6]
    if len(entries) < MIN_TIMESTAMPS:
        raise SterileError(
            f"{folder} has {len(entries)} finished timestamps in {t0:.3f}-{t1:.3f} s; the static "
            f"scene needs at least {MIN_TIMESTAMPS}: reconstruct more (--every) or widen the span"
        )
    models.require_span(entries[0].t_s, entries[-1].t_s, allow_gaps)
    regions = [Region(b, config) for b in boxes]
    frames: list[list[np.ndarray]] = [[] for _ in boxes]
    margins: list[list[np.ndarray | None]] = [[] for _ in boxes]
    observed = [load_observation(folder, e, models.seal) for e in entries]
    stored = [None if s is None else (s.points_m, s.m_per_px) for s in observed]
    evidence = "points" if all(s is not None for s in stored) else "gaussians"
    if evidence == "gaussians" and any(s is not None for s in stored):
        log.warning("%s: some timestamps were stored without their points; judging every "
                    "timestamp on its Gaussians' centres", folder)  # fmt: skip
    unknown = evidence == "gaussians" or any(s is not None and s[1] is None for s in stored)
    if config.margin_sigmas > 0 and unknown:
        log.warning("%s was made before its points kept their depth uncertainty: a point on a "
                    "box's face counts as inside it (no margin test); reconstruct the case "
                    "again for it", folder)  # fmt: skip
    with ModelSource(models, entries if evidence == "gaussians" else []) as source:
        for k, e in enumerate(entries):
            noise: np.ndarray | None = None
            if evidence == "points":
                pts, noise = stored[k]  # type: ignore[misc]
            else:
                g = source.get(e)
                keep = g.opacities().detach().numpy() >= config.min_opacity
                pts = g.means_m.detach().numpy()[keep].astype(np.float64)
            for r, reg in enumerate(regions):
                near = reg.holds(pts)
                frames[r].append(pts[near])
                margins[r].append(None if noise is None else config.margin_m(noise[near]))
            if progress is not None:
                progress(k + 1, len(entries))
    instants: dict[str, list[Instant]] = {}
    events: list[Event] = []
    aside: list[Event] = []
    stamps = [(e.t_s, e.name) for e in entries]
    eyes = [_eyes(paths, e.t_s) for e in entries]
    sights = _sights(folder, observed, config)
    for reg, pts_t, margin_t in zip(regions, frames, margins, strict=True):
        free = None if sights is None else freespace(reg, sights, [t for t, _ in stamps])
        rows, found = judge_field(reg, pts_t, margin_t, stamps, eyes, free)
        instants[reg.box.name] = rows
        events += found
        aside += set_aside(reg.box, rows, reg.config, found, eyes)
    events.sort(key=lambda ev: (ev.start_s, ev.field, ev.role))
    out.mkdir(parents=True, exist_ok=True)
    clock = CaseClock.for_case(folder, pick_zone(timezone))
    renders, seen = _event_renders(out, folder, models, events, boxes, device, paths, clock)
    cameras, note = _real_evidence(out, models, events, boxes, paths, clock, identity, seen)
    aside.sort(key=lambda ev: (ev.start_s, ev.field, ev.role))
    result = SterileResult(instants, events, renders, evidence, cameras, note, aside)
    _write_events(out / "events.csv", result)
    _write_set_aside(out / "set_aside.csv", aside)
    _write_instants(out / "instants.csv", instants)
    _plot(out / "timeline.png", result, config, clock)
    # egosurg report checks the folder's session
    write_made_for(out, folder, "sterile", "fields " + ", ".join(b.name for b in boxes))
    return result


def _sights(folder: Path, seen: list, config: SterileConfig) -> list[Sight] | None:
    """Each timestamp's points with the cameras that saw them, for the seen-empty tests; None
    (said in one warning) where they are off or the case cannot give them."""
    if config.min_air_share <= 0 and config.max_seen_through_now >= 1 and config.min_cameras < 2:
        return None
    why = ""
    if any(s is None or s.seen_by is None for s in seen):
        why = "its points were stored without the cameras that saw them (before 2026-11-29)"
    elif not (folder / "calibration.toml").is_file():
        why = "it has no calibration.toml to place its cameras"
    else:
        left = {f"SN{c.camera_serial}": c.pose.centre_m
                for c in RigCalibration.read(folder / "calibration.toml").sensors
                if c.side == "left"}  # fmt: skip
        out = []
        for s in seen:
            missing = [n for n in s.cameras if n not in left]
            if missing:
                why = f"its calibration.toml has no camera {missing[0]}"
                break
            centres = np.stack([left[n] for n in s.cameras])
            out.append(Sight(s.points_m, s.m_per_px, s.seen_by, centres))
        else:
            return out
    log.warning("%s: the seen-empty tests do not apply: %s; reconstruct the case again for "
                "them", folder, why)  # fmt: skip
    return None


STANDING_EYE = "a standing eye 1.6 m from the touch"  # the ring's viewpoints, in words


def _candidates(folder: Path, contact_m: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Eyes to judge: the rig's cameras (what was really seen), and eight around the contact."""
    out = []
    cal = folder / "calibration.toml"
    if cal.is_file():
        for s in RigCalibration.read(cal).sensors:
            if s.side == "left":
                out.append((s.name, s.pose.centre_m))
    for k in range(8):
        a = 2 * np.pi * k / 8
        eye = contact_m + np.array([1.6 * np.cos(a), 1.6 * np.sin(a), 0.0])
        eye[2] = 1.9  # a standing person's eye, looking down on the field
        out.append((STANDING_EYE, eye))  # where: on the event picture's plan
    return out


def best_viewpoint(
    g, folder: Path, raster, points_m: np.ndarray, seen: dict[str, float] | None = None
) -> tuple[str, np.ndarray, float]:
    """(name, eye, unoccluded fraction) of the candidate that sees the contact's box best;
    nearer wins a tie. ``seen`` (when given) gets each rig camera's fraction."""
    lo, hi = points_m.min(axis=0) - 0.02, points_m.max(axis=0) + 0.02
    centre = (lo + hi) / 2
    c, size = (float(v) for v in centre), (float(v) for v in hi - lo)
    box = SiteBox(name="contact", centre_m=(*c,), size_m=(*size,))  # type: ignore[arg-type]
    best: tuple[float, float, str, np.ndarray] | None = None
    for name, eye in _candidates(folder, centre):
        try:
            frac, _ = visible_fraction(g, eye, box, raster, per_face=6)
        except SightlineError:  # the eye is inside or around the contact
            continue
        if seen is not None and name != STANDING_EYE:
            seen[name] = frac
        key = (round(frac, 2), -float(np.linalg.norm(eye - centre)))
        if best is None or key > best[:2]:
            best = (*key, name, eye)
    if best is None:
        raise SterileError("no viewpoint sees the contact: the contact surrounds every camera")
    return best[2], best[3], best[0]


def _event_renders(
    out, folder, models, events, boxes, device: str, paths=(), clock: CaseClock | None = None
) -> tuple[dict[int, tuple[Path, str, float]], dict[int, dict[str, float]]]:
    """(event -> (render, viewpoint, unoccluded), event -> each rig camera's unoccluded)."""
    raster = case_raster(folder, EYE_NEAR_M, device)
    by_name = {b.name: b for b in boxes}
    renders: dict[int, tuple[Path, str, float]] = {}
    seen: dict[int, dict[str, float]] = {}
    for k, ev in enumerate(events, 1):
        if ev.sterile_role:
            continue
        peak = ev.peak
        blob, inst = ev.blobs[peak], ev.instants[peak]
        g = models.load(models.entry_at(inst.t_s))
        pts = blob.points_m[blob.in_field]
        seen[k] = {}
        name, eye, frac = best_viewpoint(g, folder, raster, pts, seen[k])
        pose = Pose.look_at(eye, pts.mean(axis=0))
        cam = Camera(name=name, intrinsics=Intrinsics.from_fov(480, 300, 55.0), pose=pose)
        rgb, _, alpha = render_view(g, cam, raster)
        rgb = show_no_data(rgb, alpha)
        outline_box(rgb, cam, by_name[ev.field])
        px, z = cam.project(pts)
        for (u, v), zz in zip(px, z, strict=True):
            if zz > 0:
                cv2.circle(rgb, (int(u), int(v)), 2, (255, 40, 40), -1, cv2.LINE_AA)
        who = ev.role or "unknown role"
        clock = clock or CaseClock.for_case(folder)
        rgb = burn_text(rgb, [
            clock.stamp(inst.t_s),
            f"event {k}: {who} in {ev.field}, {event_span(clock, ev.start_s, ev.end_s)}",
            f"shown at {clock.time_of_day(inst.t_s) or timecode(inst.t_s)} from {name} "
            f"({frac:.0%} unoccluded)",
        ])  # fmt: skip
        rgb = no_data_legend(rgb)
        plan = event_plan(folder, ev, k, boxes, pts.mean(axis=0), name, eye, paths, clock, inst.t_s)
        path = out / f"event_{k:03d}.png"
        picture = np.concatenate([rgb, plan], axis=1)
        cv2.imwrite(str(path), np.ascontiguousarray(picture[:, :, ::-1]))
        renders[k] = (path, name, frac)
    return renders, seen


def _real_evidence(
    out: Path, models: CaseModels, events: list[Event], boxes: list[SiteBox],
    paths: list[CameraPath], clock: CaseClock, identity: Identity | None,
    seen: dict[int, dict[str, float]],
) -> tuple[dict[int, CameraEvidence], str]:  # fmt: skip
    """Each contact's real camera still and clip, and "" or why there are none."""
    if all(e.sterile_role for e in events):
        return {}, ""
    lacking = "no real-camera stills or clips (event_*_camera.png, event_*_clip.mp4): "
    try:
        real = RealCameras(models, identity, clock)
    except IdentityRequiredError:
        return {}, lacking + "the case's session is sealed; give --identity FILE to add them"
    except CaseReplayError:
        return {}, lacking + (f"the case's session {models.index.session} or its "
                              "calibration.toml is gone; put them back to add them")  # fmt: skip
    by_name = {b.name: b for b in boxes}
    roles = {p.name: p for p in paths}
    found = {}
    try:
        for k, ev in enumerate(events, 1):
            role = roles.get(ev.role)
            if ev.sterile_role:
                continue
            eye = (lambda t, p=role: _eye(p, t)) if role is not None else None
            made = camera_evidence(out, k, ev, by_name[ev.field], real, clock, seen.get(k, {}), eye)
            if made is not None:
                found[k] = made
    finally:
        real.close()
    return found, ""


def _write_events(path: Path, result: SterileResult) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["event", "field", "kind", "role", "role_distance_m", "start_s", "end_s",
                    "timestamps", "peak_t_s", "peak_points", "contact_x_m", "contact_y_m",
                    "contact_z_m", "viewpoint", "unoccluded_fraction", "render",
                    "camera", "camera_still", "clip", "clip_from_s", "clip_to_s"])  # fmt: skip
        for k, ev in enumerate(result.events, 1):
            blob, inst = ev.blobs[ev.peak], ev.instants[ev.peak]
            png, view, frac = result.renders.get(k, (None, "", float("nan")))
            real = result.cameras.get(k)
            seen = ["", "", "", "", ""]
            if real is not None and real.clip is not None:
                seen = [real.camera, real.still.name, real.clip.name, f"{real.clip_from_s:.3f}",
                        f"{real.clip_to_s:.3f}"]  # fmt: skip
            elif real is not None:
                seen = [real.camera, real.still.name, "", "", ""]
            w.writerow([
                k, ev.field, "sterile-role" if ev.sterile_role else "contact", ev.role,
                f"{blob.role_distance_m:.2f}", f"{ev.start_s:.3f}", f"{ev.end_s:.3f}",
                len(ev.instants), f"{inst.t_s:.3f}", blob.count,
                *(f"{v:.3f}" for v in blob.contact_m), view, f"{frac:.2f}",
                png.name if png else "", *seen,
            ])  # fmt: skip


def _write_set_aside(path: Path, events: list[Event]) -> None:
    """The candidate contacts test 6 set aside, each with its least ``filled_before`` (the
    share of the 0.5-2 s before at which its crossing into the box was filled)."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["field", "role", "start_s", "end_s", "timestamps", "peak_t_s", "peak_points",
                    "contact_x_m", "contact_y_m", "contact_z_m", "filled_before"])  # fmt: skip
        for ev in events:
            blob, inst = ev.blobs[ev.peak], ev.instants[ev.peak]
            least = min(b.filled_before for b in ev.blobs)
            w.writerow([ev.field, ev.role, f"{ev.start_s:.3f}", f"{ev.end_s:.3f}",
                        len(ev.instants), f"{inst.t_s:.3f}", blob.count,
                        *(f"{v:.3f}" for v in blob.contact_m), f"{least:.3f}"])  # fmt: skip


def _write_instants(path: Path, instants: dict[str, list[Instant]]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "model", "field", "moving_points_in_field", "blobs", "roles"])
        for name, rows in instants.items():
            for i in rows:
                roles = ";".join(f"{b.role or '?'}:{b.count}" for b in i.blobs)
                w.writerow([f"{i.t_s:.3f}", i.model, name, i.moving_in_field, len(i.blobs), roles])


def _plot(
    path: Path, result: SterileResult, config: SterileConfig, clock: CaseClock | None = None
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fields = list(result.instants)
    fig, axes = plt.subplots(len(fields), 1, figsize=(8, 2.6 * len(fields)), dpi=110,
                             squeeze=False)  # fmt: skip
    roles = list(dict.fromkeys(e.role for e in result.events if not e.sterile_role))
    for ax, name in zip(axes[:, 0], fields, strict=True):
        rows = result.instants[name]
        t = np.array([i.t_s for i in rows])
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.5
        ax.plot(t, [i.moving_in_field for i in rows], "-", color="0.3", lw=1,
                label="moving points in the field")  # fmt: skip
        ax.axhline(config.min_points, color="grey", ls=":", lw=1)
        for ev in (e for e in result.events if e.field == name):
            span = (ev.start_s - dt / 2, ev.end_s + dt / 2)
            if ev.sterile_role:  # allowed: a thin grey strip along the bottom
                ax.axvspan(*span, ymin=0, ymax=0.05, color="0.55", lw=0)
            else:
                colour = f"C{roles.index(ev.role) % 10}"
                ax.axvspan(*span, color=colour, alpha=0.3, lw=0)
        for role in roles:
            ax.plot([], [], "s", color=f"C{roles.index(role) % 10}", alpha=0.5,
                    label=role or "contact")  # fmt: skip
        ax.set(xlabel="case time (s)", ylabel="moving points")
        ax.set_title(f"{name}: contacts shaded by role (grey strip: sterile roles)", fontsize=10)
        ax.legend(fontsize=7, loc="upper right")
        if clock is not None:
            add_time_of_day_axis(ax, clock)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def read_roles(
    path: str | None, sterile_roles: tuple[str, ...], inputs: CaseInputs | None = None
) -> list[CameraPath]:
    """The roles of ``path``; with ``inputs``, checked to be made for its case's session."""
    from protocol.formats.trajectory import read_trajectories

    if path is None:
        if sterile_roles:
            raise SterileError("--sterile-roles needs --roles (a roles TOML naming them)")
        return []
    found = inputs.trajectories(path) if inputs is not None else read_trajectories(path)
    paths = [CameraPath(t) for t in found]
    names = [p.name for p in paths]
    unknown = [r for r in sterile_roles if r not in names]
    if unknown:
        raise SterileError(f"no role {unknown[0]!r} in {path}; it has: {', '.join(names)}")
    return paths
