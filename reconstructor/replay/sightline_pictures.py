"""``sightline``'s pictures: a top-down plan with each answer, and views aimed at the target.

Each timestamp's answer gets ``plan_<t>.png``: the room from above (the rig's extent, the site's
boxes, every role where they stood), the viewer and the target, the line between them in green
where at least half the target is visible and red where not, and the people who stand on it
circled, by role (``plan.who_blocks``), with the answer in words ("no obstruction", or "blocked
by circulator (55 % of monitor-a)"). The worst instants' ``worst_<t>.png`` put the views from
the viewer's position(s) beside that plan; each view is aimed at the target with the viewer's
field of view, so the target is in the picture even when they faced away (the label says how
far they would have had to turn).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Camera, Intrinsics, Pose
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.site import SiteBox
from reconstructor.replay.clock import CaseClock
from reconstructor.replay.frame import no_data_legend, show_no_data
from reconstructor.replay.path import CameraPath
from reconstructor.replay.plan import PlanItems, describe_blockers, plan_picture
from reconstructor.replay.run import render_view
from reconstructor.replay.video import burn_text, timecode

VISIBLE_ENOUGH = 0.5  # "at least half visible": sightline's binary answer
PLAN_SIZE_PX = (480, 420)


@dataclass
class SightScene:
    """What the plans show besides the viewer and the target."""

    cameras_m: np.ndarray | None  # the rig's left cameras, (N, 3)
    boxes: tuple[SiteBox, ...]  # the site's other boxes
    others: tuple[CameraPath, ...]  # the other roles
    clock: CaseClock

    @classmethod
    def for_case(
        cls, folder: Path, boxes: tuple[SiteBox, ...], others: tuple[CameraPath, ...],
        clock: CaseClock,
    ) -> SightScene:  # fmt: skip
        cal = folder / "calibration.toml"
        cams = None
        if cal.is_file():
            sensors = [s for s in RigCalibration.read(cal).sensors if s.side == "left"]
            cams = np.array([s.pose.centre_m for s in sensors]) if sensors else None
        return cls(cams, boxes, others, clock)

    def people_at(self, t_s: float, viewer: str) -> dict[str, np.ndarray]:
        """Each other role's eye at ``t_s`` (held at its first or last keyframe outside them;
        a role inside one of its gaps is nowhere known, and left out)."""
        return {
            p.name: p.pose(float(np.clip(t_s, *p.span_s))).centre_m
            for p in self.others
            if p.name != viewer and p.gap_at(t_s) is None
        }


def answer_plan(
    rows, viewer: str, box: SiteBox, scene: SightScene, size_px=PLAN_SIZE_PX, path=None
):
    """The plan of one timestamp's answers (``rows``: its SightRows, actual first); with the
    viewer's ``path``, an arrow where they faced."""
    t_s = rows[0].t_s
    items = PlanItems(
        title=f"{viewer} -> {box.name}, {_when(scene.clock, t_s)}",
        cameras_m=scene.cameras_m,
        boxes=[(b, "C1") for b in scene.boxes if b.name != box.name] + [(box, "C4")],
        people=scene.people_at(t_s, viewer),
    )
    centre = np.asarray(box.centre_m, float)
    words = []
    for k, r in enumerate(rows):
        eye = np.asarray(r.eye_m, float)
        seen = r.visible_fraction >= VISIBLE_ENOUGH
        name = f"{viewer} ({r.position})"
        items.lines.append((eye, centre, "C2" if seen else "C3", "line of sight" if k == 0 else ""))
        items.marks.append((eye, "o" if k == 0 else "s", "C0", name))
        if path is not None:
            items.facing.append((eye, path.pose(float(np.clip(t_s, *path.span_s))).R[2]))
        items.circled += [role for role, _ in r.blockers]  # people among them are circled
        words.append(f"{r.position}: {r.visible_fraction:.0%} visible, "
                     f"{describe_blockers(dict(r.blockers), box.name)}")  # fmt: skip
    items.caption = "\n".join(words)
    return plan_picture(items, size_px)


def aimed_view(g, eye_m, box: SiteBox, fov_deg: float, size_px, raster) -> np.ndarray:
    """A render from ``eye_m`` aimed at the box's centre with the viewer's field of view, the
    no-data hatch and the box outlined."""
    pose = Pose.look_at(np.asarray(eye_m, float), np.asarray(box.centre_m, float))
    w, h = size_px
    cam = Camera(name="aimed", intrinsics=Intrinsics.from_fov(w, h, fov_deg), pose=pose)
    rgb, _, alpha = render_view(g, cam, raster)
    rgb = show_no_data(rgb, alpha)
    outline_box(rgb, cam, box)
    return rgb


def turn_deg(path: CameraPath, t_s: float, eye_m, box: SiteBox) -> float:
    """How far the viewer would turn, from where they faced, to look at the box's centre."""
    forward = path.pose(t_s).R[2]
    to = np.asarray(box.centre_m, float) - np.asarray(eye_m, float)
    cos = float(forward @ to / max(np.linalg.norm(to), 1e-9))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def worst_picture(rows, path: CameraPath, box: SiteBox, g, raster, size_px, scene: SightScene):
    """Views from each position at one instant, aimed at the target, beside its plan."""
    t_s = rows[0].t_s
    fov = path.fov_deg(t_s)
    panels = []
    for r in rows:
        rgb = aimed_view(g, r.eye_m, box, fov, size_px, raster)
        turn = turn_deg(path, t_s, r.eye_m, box)
        facing = "in front of them" if turn < fov / 2 else f"they faced {turn:.0f} deg away"
        rgb = burn_text(rgb, [
            scene.clock.stamp(t_s),
            f"case time {timecode(t_s)}  {path.name} {r.position}",
            f"looking at {box.name} ({facing}): {r.visible_fraction:.0%} visible",
            describe_blockers(dict(r.blockers), box.name),
        ])  # fmt: skip
        panels.append(no_data_legend(rgb))
    views = np.concatenate(panels, axis=1)
    plan = answer_plan(rows, path.name, box, scene, PLAN_SIZE_PX, path)
    h = max(views.shape[0], plan.shape[0])
    canvas = np.full((h, views.shape[1] + plan.shape[1], 3), 255, np.uint8)
    canvas[: views.shape[0], : views.shape[1]] = views
    canvas[: plan.shape[0], views.shape[1] :] = plan
    return canvas


def _when(clock: CaseClock, t_s: float) -> str:
    return clock.time_of_day(t_s) or f"{t_s:.3f} s"


def outline_box(rgb: np.ndarray, cam, box: SiteBox) -> None:
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / 2
    pts = (c * np.asarray(box.size_m)) @ box.rotation.T + np.asarray(box.centre_m)
    px, z = cam.project(pts)
    if np.any(z <= 0.05):
        return
    for a in range(8):
        for b in range(a + 1, 8):
            if bin(a ^ b).count("1") == 1:  # corners differing in one axis share an edge
                p, q = tuple(int(v) for v in px[a]), tuple(int(v) for v in px[b])
                cv2.line(rgb, p, q, (255, 210, 0), 2, cv2.LINE_AA)
