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

from protocol.formats.camera_config import SIM_PHASES
from sim.errors import UnknownPhaseError
from sim.people import Person, Waypoint

PHASES = SIM_PHASES  # a sim camera table names one of them (node.toml's contract)

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


@dataclass(frozen=True)
class PhaseScript:
    name: str
    people: tuple[Person, ...]
    with_patient: bool
    with_wand: bool
    with_mobile_equipment: bool = True  # the robot cart and the C-arm


class _Draws:
    """The seeded variations of one phase's script. The draws happen in the order the script
    states its people (each waypoint's x, y and dwell, then the person's height and start), so
    a seed gives the same scene as it always has."""

    def __init__(self, seed: int) -> None:
        self._rng = np.random.default_rng([seed, 0x9A5E])

    def jitter(self, v: float, amp: float = 0.08) -> float:
        return float(v + self._rng.uniform(-amp, amp))

    def wp(
        self,
        x: float,
        y: float,
        dwell: float,
        focus: tuple[float, float, float] = TABLE,
        working: bool = False,
    ) -> Waypoint:
        return Waypoint(
            x_m=self.jitter(x),
            y_m=self.jitter(y),
            dwell_s=self.jitter(dwell, 0.5),
            focus_xyz_m=focus,
            working=working,
        )

    def person(
        self,
        name: str,
        role: str,
        tint: tuple[float, float, float],
        cap: tuple[float, float, float],
        height: float,
        wps: list[Waypoint],
        offset: float = 0.0,
    ) -> Person:
        return Person(
            name=name,
            role=role,
            scrub_tint=tint,
            cap_tint=cap,
            height_m=self.jitter(height, 0.05),
            waypoints=tuple(wps),
            start_offset_s=self.jitter(offset, 1.0) % 60,
        )


def phase_script(name: str, seed: int) -> PhaseScript:
    if name not in PHASES:
        raise UnknownPhaseError(f"unknown phase {name!r}; the phases are {', '.join(PHASES)}")
    if name == "empty":
        return PhaseScript(name, (), with_patient=False, with_wand=False)
    if name == "wand":
        return PhaseScript(
            name, (), with_patient=False, with_wand=True, with_mobile_equipment=False
        )
    draws = _Draws(seed)
    if name == "setup":
        return PhaseScript(name, _setup_people(draws), with_patient=True, with_wand=False)
    if name == "intraoperative":
        return PhaseScript(name, _intraoperative_people(draws), with_patient=True, with_wand=False)
    return PhaseScript(name, _turnover_people(draws), with_patient=False, with_wand=False)


def _setup_people(r: _Draws) -> tuple[Person, ...]:
    """Three staff prepare the room and the back table."""
    return (
        r.person(
            "nurse_scrub",
            "scrub nurse",
            GOWN,
            CAP_BLUE,
            1.68,
            [
                r.wp(-1.3, 1.45, 6.0, BACK_TABLE, True),
                r.wp(-0.4, 0.7, 3.0, TABLE, True),
                r.wp(-1.9, 1.4, 4.0, BACK_TABLE, True),
            ],
        ),
        r.person(
            "circulator",
            "circulating nurse",
            SCRUB_CEIL,
            CAP_PRINT,
            1.63,
            [
                r.wp(2.6, -2.2, 2.0, MONITOR_A),
                r.wp(1.2, -0.8, 4.0, TABLE, True),
                r.wp(-1.0, -1.1, 3.0, ANAESTHESIA),
                r.wp(2.2, 1.8, 2.5, TABLE),
            ],
            4.0,
        ),
        r.person(
            "anaesthetist",
            "anaesthetist",
            SCRUB_NAVY,
            CAP_BLUE,
            1.80,
            [r.wp(-1.35, -0.15, 8.0, TABLE, True), r.wp(-1.5, -1.2, 5.0, ANAESTHESIA, True)],
        ),
    )


def _intraoperative_people(r: _Draws) -> tuple[Person, ...]:
    """The crowded phase: six people around the patient."""
    return (
        r.person(
            "surgeon",
            "surgeon",
            GOWN,
            CAP_PRINT,
            1.82,
            [r.wp(0.25, -0.62, 14.0, TABLE, True), r.wp(0.55, -0.68, 6.0, MONITOR_A, True)],
        ),
        r.person(
            "assistant",
            "assistant",
            GOWN,
            CAP_BLUE,
            1.72,
            [r.wp(0.2, 0.62, 12.0, TABLE, True), r.wp(-0.25, 0.65, 5.0, TABLE, True)],
            3.0,
        ),
        r.person(
            "anaesthetist",
            "anaesthetist",
            SCRUB_NAVY,
            CAP_BLUE,
            1.78,
            [r.wp(-1.35, -0.2, 9.0, TABLE, True), r.wp(-1.6, -1.15, 6.0, ANAESTHESIA, True)],
        ),
        r.person(
            "nurse_scrub",
            "scrub nurse",
            GOWN,
            CAP_PRINT,
            1.66,
            [r.wp(-0.9, 1.35, 7.0, BACK_TABLE, True), r.wp(-0.35, 0.75, 3.0, TABLE, True)],
            2.0,
        ),
        r.person(
            "circulator",
            "circulating nurse",
            SCRUB_CEIL,
            CAP_BLUE,
            1.62,
            [
                r.wp(2.5, -2.1, 3.0, MONITOR_A),
                r.wp(1.8, 0.4, 2.0, TABLE),
                r.wp(2.4, 2.0, 4.0, TABLE),
                r.wp(-2.5, 0.8, 3.0, ANAESTHESIA),
            ],
            6.0,
        ),
        r.person(
            "robot_assistant",
            "bedside assistant",
            SCRUB_TEAL,
            CAP_PRINT,
            1.75,
            [r.wp(1.55, 0.35, 8.0, TABLE, True), r.wp(1.6, -0.5, 5.0, MONITOR_A)],
        ),
    )


def _turnover_people(r: _Draws) -> tuple[Person, ...]:
    """The patient has left: three staff clean and restock."""
    return (
        r.person(
            "cleaner_a",
            "environmental services",
            SCRUB_GREEN,
            CAP_BLUE,
            1.7,
            [
                r.wp(0.6, -0.7, 5.0, TABLE, True),
                r.wp(-0.6, -0.7, 5.0, TABLE, True),
                r.wp(-0.6, 0.7, 5.0, TABLE, True),
                r.wp(0.6, 0.7, 5.0, TABLE, True),
            ],
        ),
        r.person(
            "cleaner_b",
            "environmental services",
            SCRUB_GREEN,
            CAP_PRINT,
            1.76,
            [
                r.wp(2.3, -2.0, 3.0, (3.0, -3.0, 0.3), True),
                r.wp(2.5, 1.6, 3.0, (3.5, 2.0, 0.3), True),
                r.wp(-2.4, 1.4, 3.0, (-3.0, 2.0, 0.3), True),
            ],
        ),
        r.person(
            "circulator",
            "circulating nurse",
            SCRUB_CEIL,
            CAP_BLUE,
            1.64,
            [r.wp(-1.0, 1.35, 6.0, BACK_TABLE, True), r.wp(2.8, -1.2, 4.0, (3.5, -1.2, 1.0))],
            2.0,
        ),
    )
