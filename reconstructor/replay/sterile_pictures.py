"""``sterile``'s event pictures, for a team to read: the render of the touch carries the date,
the time of day and the case's id, and beside it a plan from above shows the field, the rig,
where each role stood, who touched (circled), where the touch was and where the picture was
taken from, so a viewpoint named in words ("a standing eye 1.6 m from the touch") is found in
the room without its coordinates."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from protocol.formats.site import SiteBox
from reconstructor.replay.clock import CaseClock
from reconstructor.replay.plan import PlanItems, plan_picture
from reconstructor.replay.sightline_pictures import SightScene
from reconstructor.replay.video import timecode_span

PLAN_SIZE_PX = (340, 300)  # beside the 480 x 300 render


def event_span(clock: CaseClock, start_s: float, end_s: float) -> str:
    """``09:00:06.320 - 09:00:07.280 UTC``, or ``at 09:00:07.000 UTC`` for one time; case
    time when the case records no start."""
    if not clock.known:
        return timecode_span(start_s, end_s)
    a, b = clock.time_of_day(start_s), clock.time_of_day(end_s)
    if a == b:
        return f"at {a}"
    return f"{a.rsplit(' ', 1)[0]} - {b}"


def event_plan(
    folder: Path, event, number: int, boxes: list[SiteBox], contact_m: np.ndarray,
    viewpoint: str, eye_m: np.ndarray, paths, clock: CaseClock, t_s: float,
) -> np.ndarray:  # fmt: skip
    """(300, 340, 3) uint8 RGB: the plan of event ``number`` at ``t_s``."""
    scene = SightScene.for_case(folder, (), tuple(paths), clock)
    items = PlanItems(
        title=f"event {number}: {event.role or 'unknown role'} in {event.field}",
        caption=f"shown from {viewpoint}",
        cameras_m=scene.cameras_m,
        boxes=[(b, "C3" if b.name == event.field else "C1") for b in boxes],
        people=scene.people_at(t_s, viewer=""),
        circled=[event.role] if event.role else [],
    )
    items.lines.append((np.asarray(eye_m), np.asarray(contact_m), "C0", ""))
    items.marks.append((np.asarray(eye_m), "o", "C0", "viewpoint"))
    items.marks.append((np.asarray(contact_m), "X", "C3", "the touch"))
    return plan_picture(items, PLAN_SIZE_PX)
