"""The case's facts and its session's health, for the report's first two sections.

Case id, room, date and time of day come from the case's session: its ``session_name`` (the
name given at ``egosurg record start --case``), a ``room`` case-metadata value or the rig's
``rig_name``, and ``started_unix_ns``. Times in the report are shown both as case time (seconds
since the session started, what every other tool prints) and as the time of day in the zone
the reviewer asks for (``--timezone``, default the machine's). The health is
``protocol.session.health.summarise``, the same numbers ``egosurg session info`` prints.
"""

from __future__ import annotations

import datetime as dt
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.errors import ConfigError, UserError
from protocol.formats.rig_calibration import RigCalibration
from protocol.sealing import Identity
from protocol.toml_config import parse_toml
from reconstructor.errors import CaseReplayError
from reconstructor.replay.clock import CaseClock
from reconstructor.replay.models import CaseModels

log = logging.getLogger(__name__)
SEALED = "<sealed>"  # how a sealed session's metadata value reads without an identity


class ReportInputError(UserError, ValueError):
    """An input of ``egosurg report`` that cannot be used; the message says what to give."""


@dataclass(frozen=True)
class CaseFacts:
    case_folder: Path
    session_path: Path
    case_id: str
    room: str
    clock: CaseClock  # case time to time of day (replay/clock.py, as replay burns it in)
    span_s: tuple[float, float]  # the case's first and last done timestamp
    timestamps_done: int
    timestamps_planned: int
    spacing_s: float
    health: dict[str, Any] | None  # summarise(); None when the session file is gone
    sealed: bool  # a sealed session read without an identity: no images, metadata sealed
    recipients: str = ""
    calibration: dict[str, Any] = field(default_factory=dict)  # [quality] of calibration.toml

    @property
    def date(self) -> str:
        return self.clock.at(0.0).strftime("%Y-%m-%d, %A")

    @property
    def zone_name(self) -> str:
        """``CET (UTC+0100)``: the zone the page's times of day are in."""
        return self.clock.at(0.0).strftime("%Z (UTC%z)")


def read_facts(folder: Path, identity: Identity | None, zone: dt.tzinfo) -> CaseFacts:
    """The facts of the case at ``folder``; its session is read where the case records it."""
    from protocol.session import SessionReader
    from protocol.session.health import summarise

    try:
        models = CaseModels(folder, identity)  # a sealed case: refused without it
    except CaseReplayError as exc:
        raise ReportInputError(str(exc)) from None
    index = models.index
    session = Path(index.session)
    health, sealed, recipients, name, room = None, False, "", "", ""
    started = index.session_started_unix_ns
    if session.is_file():
        with SessionReader(session, identity=identity) as reader:
            health = summarise(reader)
            info = reader.info
            name, started = info.session_name, info.started_unix_ns
            room = _room(info.case_metadata, info.rig_config_toml)
            sealed = not reader.can_open
            recipients = ", ".join(r.label() for r in reader.recipients) if sealed else ""
    else:
        log.warning("the case's session %s is gone: the report has no session health and no "
                    "real camera frames", session)  # fmt: skip
    if started <= 0:
        raise ReportInputError(
            f"{folder}'s session start is unknown (the case records none and {session} is "
            "gone): the report cannot give times of day; put the session back at that path"
        )
    return CaseFacts(
        case_folder=folder, session_path=session, case_id=name or session.stem, room=room,
        clock=CaseClock(case_id=name or session.stem, started_unix_ns=started, zone=zone),
        span_s=models.span_s, timestamps_done=len(models.entries),
        timestamps_planned=len(models.all_entries), spacing_s=models.spacing_s, health=health,
        sealed=sealed, recipients=recipients, calibration=_calibration(folder),
    )  # fmt: skip


def _room(metadata: dict[str, str], rig_toml: str) -> str:
    """The ``room`` metadata value, else the rig's name (a rig is one room's cameras)."""
    if metadata.get("room"):
        return metadata["room"]
    if rig_toml == SEALED:
        return SEALED
    try:
        return str(parse_toml(rig_toml, "the rig text").get("rig_name", "")) if rig_toml else ""
    except ConfigError:  # the room is a nicety: a damaged rig text leaves it unnamed
        return ""


def _calibration(folder: Path) -> dict[str, Any]:
    """The calibration's ``[quality]`` (verdict, reprojection error, wand score) and its sensor
    count; empty when the case holds no calibration.toml."""
    path = folder / "calibration.toml"
    if not path.is_file():
        return {}
    cal = RigCalibration.read(path)
    return {**cal.quality, "sensors": len(cal.sensors), "cameras": len(cal.camera_serials)}
