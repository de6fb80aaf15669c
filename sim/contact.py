"""A scripted sterile-field contact: a non-sterile radiographer reaches out and touches the
drape's edge at known times, and the exact truth of when any body enters the drape's box.

Off by default (``WorldConfig(contact=True)`` or ``egosurg sim eval-set --contact`` turns it
on), so the existing scenes and the numbers measured on them do not change. The radiographer
stands beside the foot end of the table on the surgeon's side, away from the sterile team,
arms at rest; at each scripted touch the right hand moves to the drape's edge in ``reach_s``,
stays there and goes back. Touches repeat every ``period_s`` (60 s), so a longer case holds
more of them.

The truth is geometric, not the script's times: a person is in the field while any vertex of
their body's meshes lies inside the field box, found on a 50 ms grid and refined by bisection
to 1 ms. It covers every person of the scene, so a test can check that only the scripted
touches enter the field.

``egosurg sim contact SESSION.h5 --field-out field.toml --truth-out contact.csv``
(``sim/contact_cli.py``) writes the field box (a site file, ``protocol/formats/site.py``) and the
true intervals over the session's span.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.formats.site import SiteBox
from sim.geometry import rot_z
from sim.people import Person, PersonState, Waypoint, person_objects, person_state
from sim.room import SceneObject

# The drape over the patient, from the head-end screen (x = -0.72 m, the sterile boundary) to
# the foot end, out to its hanging edges (y = +-0.45 m), up to 1 m: below the sterile team's
# working hands (about 1.15 m), so that their work over the patient is not a contact.
DRAPE_FIELD = SiteBox(name="drape", centre_m=(0.17, 0.0, 0.81), size_m=(1.78, 0.92, 0.38))
TOUCH_POINT_M = (0.92, -0.33, 0.96)  # on the drape at the table edge, surgeon side, near the foot
# (start of the reach, seconds the hand is away from rest) within each period
TOUCHES_S = ((6.0, 1.6), (19.5, 2.6), (33.0, 1.3), (47.5, 3.2))


@dataclass(frozen=True, kw_only=True)
class ContactScript:
    """A person who stands still and reaches the right hand to ``touch_point_m`` at scripted
    times: each touch leaves rest at ``start_s``, is at the point from ``start_s + reach_s`` to
    ``start_s + away_s - reach_s`` and back at rest at ``start_s + away_s``."""

    person: Person
    touch_point_m: tuple[float, float, float] = TOUCH_POINT_M
    touches_s: tuple[tuple[float, float], ...] = TOUCHES_S
    period_s: float = 60.0
    reach_s: float = 0.5

    def __post_init__(self) -> None:
        for start, away in self.touches_s:
            if not (0 <= start and start + away <= self.period_s and away > 2 * self.reach_s):
                raise ValueError(
                    f"touch ({start}, {away}): inside one period, longer than 2 reaches"
                )

    def reach_amount(self, t_s: float) -> float:
        """0 at rest .. 1 at the touch point (smoothstep in and out)."""
        tl = t_s % self.period_s
        for start, away in self.touches_s:
            if start <= tl <= start + away:
                u = min(tl - start, start + away - tl) / self.reach_s
                u = float(np.clip(u, 0.0, 1.0))
                return u * u * (3 - 2 * u)
        return 0.0

    def state(self, t_s: float) -> PersonState:
        return person_state(self.person, t_s)

    def objects(self, t_s: float) -> list[SceneObject]:
        state = self.state(t_s)
        amount = self.reach_amount(t_s)
        if amount <= 0.0:
            return person_objects(self.person, state)
        rest = _rest_right_hand(state)
        target = rest + amount * (np.asarray(self.touch_point_m) - rest)
        return person_objects(self.person, state, hand_target_m=target)


def _rest_right_hand(state: PersonState) -> np.ndarray:
    """Where ``person_objects`` puts a standing person's right hand (arms hanging)."""
    s = state.scale
    local = np.array([0.0, -0.21, 1.43]) + 0.3 * np.array([0.0, 0.0, -1.0])
    local = local + 0.27 * np.array([0.25, 0.0, -1.0])
    x, y = state.position_xy_m
    return rot_z(state.heading_rad) @ (local * s) + np.array([x, y, 0.0])


def contact_script(seed: int) -> ContactScript:
    """The default script; the seed is kept for a later variation and does not change it."""
    del seed
    radiographer = Person(
        name="radiographer",
        role="radiographer (non-sterile)",
        scrub_tint=(0.55, 0.35, 0.55),
        cap_tint=(0.8, 0.35, 0.45),
        height_m=1.74,
        waypoints=(Waypoint(x_m=1.02, y_m=-0.98, dwell_s=60.0, focus_xyz_m=TOUCH_POINT_M),),
    )
    return ContactScript(person=radiographer)
