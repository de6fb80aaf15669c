"""Workflow phases: who is in the room and what they do.

- ``empty``: the room between cases, nobody in it;
- ``setup``: three staff prepare the room and the back table; the patient is on the table;
- ``intraoperative``: the crowded phase: surgeon, assistant, anaesthetist, scrub nurse, circulator
  and a robot-side assistant around the patient;
- ``turnover``: the patient has left; three staff clean and restock;
- ``wand``: a calibration session: the mobile equipment (robot cart, C-arm) is pushed aside, as
  sites do before calibrating, and one operator waves the wand through the open space over the
  table.

Each phase is a list of people with closed waypoint loops, slightly varied by the seed so that
different seeds give different (but equally plausible) scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.errors import UserError
from sim.people import Person, Waypoint

PHASES = ("empty", "setup", "intraoperative", "turnover", "wand")

TABLE = (0.0, 0.0, 0.95)
BACK_TABLE = (-1.3, 1.95, 0.9)
MONITOR_A = (1.7, -1.35, 1.75)
ANAESTHESIA = (-2.0, -0.75, 1.2)

GOWN = (0.45, 0.62, 0.78)
SCRUB_NAVY = (0.18, 0.24, 0.45)
SCRUB_TEAL = (0.25, 0.58, 0.6)
SCRUB_CEIL = (0.52, 0.66, 0.86)
SCRUB_GREEN = (0.35, 0.6, 0.45)
CAP_BLUE = (0.35, 0.5, 0.85)
CAP_PRINT = (0.8, 0.35, 0.45)


class UnknownPhaseError(UserError, ValueError):
    pass


@dataclass(frozen=True)
class PhaseScript:
    name: str
    people: tuple[Person, ...]
    with_patient: bool
    with_wand: bool
    with_mobile_equipment: bool = True  # the robot cart and the C-arm


def phase_script(name: str, seed: int) -> PhaseScript:
    if name not in PHASES:
        raise UnknownPhaseError(f"unknown phase {name!r}; the phases are {', '.join(PHASES)}")
    rng = np.random.default_rng([seed, 0x9A5E])

    def j(v: float, amp: float = 0.08) -> float:
        return float(v + rng.uniform(-amp, amp))

    def wp(x: float, y: float, dwell: float, focus=TABLE, working: bool = False) -> Waypoint:
        return Waypoint(
            x_m=j(x), y_m=j(y), dwell_s=j(dwell, 0.5), focus_xyz_m=focus, working=working
        )

    def person(name, role, tint, cap, height, wps, offset=0.0) -> Person:
        return Person(
            name=name,
            role=role,
            scrub_tint=tint,
            cap_tint=cap,
            height_m=j(height, 0.05),
            waypoints=tuple(wps),
            start_offset_s=j(offset, 1.0) % 60,
        )

    if name == "empty":
        return PhaseScript(name, (), with_patient=False, with_wand=False)
    if name == "wand":
        return PhaseScript(
            name, (), with_patient=False, with_wand=True, with_mobile_equipment=False
        )
    if name == "setup":
        people: tuple[Person, ...] = (
            person(
                "nurse_scrub",
                "scrub nurse",
                GOWN,
                CAP_BLUE,
                1.68,
                [
                    wp(-1.3, 1.45, 6.0, BACK_TABLE, True),
                    wp(-0.4, 0.7, 3.0, TABLE, True),
                    wp(-1.9, 1.4, 4.0, BACK_TABLE, True),
                ],
            ),
            person(
                "circulator",
                "circulating nurse",
                SCRUB_CEIL,
                CAP_PRINT,
                1.63,
                [
                    wp(2.6, -2.2, 2.0, MONITOR_A),
                    wp(1.2, -0.8, 4.0, TABLE, True),
                    wp(-1.0, -1.1, 3.0, ANAESTHESIA),
                    wp(2.2, 1.8, 2.5, TABLE),
                ],
                4.0,
            ),
            person(
                "anaesthetist",
                "anaesthetist",
                SCRUB_NAVY,
                CAP_BLUE,
                1.80,
                [wp(-1.35, -0.15, 8.0, TABLE, True), wp(-1.5, -1.2, 5.0, ANAESTHESIA, True)],
            ),
        )
        return PhaseScript(name, people, with_patient=True, with_wand=False)
    if name == "intraoperative":
        people = (
            person(
                "surgeon",
                "surgeon",
                GOWN,
                CAP_PRINT,
                1.82,
                [wp(0.25, -0.62, 14.0, TABLE, True), wp(0.55, -0.68, 6.0, MONITOR_A, True)],
            ),
            person(
                "assistant",
                "assistant",
                GOWN,
                CAP_BLUE,
                1.72,
                [wp(0.2, 0.62, 12.0, TABLE, True), wp(-0.25, 0.65, 5.0, TABLE, True)],
                3.0,
            ),
            person(
                "anaesthetist",
                "anaesthetist",
                SCRUB_NAVY,
                CAP_BLUE,
                1.78,
                [wp(-1.35, -0.2, 9.0, TABLE, True), wp(-1.6, -1.15, 6.0, ANAESTHESIA, True)],
            ),
            person(
                "nurse_scrub",
                "scrub nurse",
                GOWN,
                CAP_PRINT,
                1.66,
                [wp(-0.9, 1.35, 7.0, BACK_TABLE, True), wp(-0.35, 0.75, 3.0, TABLE, True)],
                2.0,
            ),
            person(
                "circulator",
                "circulating nurse",
                SCRUB_CEIL,
                CAP_BLUE,
                1.62,
                [
                    wp(2.5, -2.1, 3.0, MONITOR_A),
                    wp(1.8, 0.4, 2.0, TABLE),
                    wp(2.4, 2.0, 4.0, TABLE),
                    wp(-2.5, 0.8, 3.0, ANAESTHESIA),
                ],
                6.0,
            ),
            person(
                "robot_assistant",
                "bedside assistant",
                SCRUB_TEAL,
                CAP_PRINT,
                1.75,
                [wp(1.55, 0.35, 8.0, TABLE, True), wp(1.6, -0.5, 5.0, MONITOR_A)],
            ),
        )
        return PhaseScript(name, people, with_patient=True, with_wand=False)
    # turnover
    people = (
        person(
            "cleaner_a",
            "environmental services",
            SCRUB_GREEN,
            CAP_BLUE,
            1.7,
            [
                wp(0.6, -0.7, 5.0, TABLE, True),
                wp(-0.6, -0.7, 5.0, TABLE, True),
                wp(-0.6, 0.7, 5.0, TABLE, True),
                wp(0.6, 0.7, 5.0, TABLE, True),
            ],
        ),
        person(
            "cleaner_b",
            "environmental services",
            SCRUB_GREEN,
            CAP_PRINT,
            1.76,
            [
                wp(2.3, -2.0, 3.0, (3.0, -3.0, 0.3), True),
                wp(2.5, 1.6, 3.0, (3.5, 2.0, 0.3), True),
                wp(-2.4, 1.4, 3.0, (-3.0, 2.0, 0.3), True),
            ],
        ),
        person(
            "circulator",
            "circulating nurse",
            SCRUB_CEIL,
            CAP_BLUE,
            1.64,
            [wp(-1.0, 1.35, 6.0, BACK_TABLE, True), wp(2.8, -1.2, 4.0, (3.5, -1.2, 1.0))],
            2.0,
        ),
    )
    return PhaseScript(name, people, with_patient=False, with_wand=False)
