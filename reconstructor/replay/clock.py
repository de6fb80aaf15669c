"""Case time as a team reads it: the time of day and the case's id.

Every review tool counts case time in seconds since the session started (``t_s`` in the case
index). A picture shown to a surgical team says when that was on the wall clock, from the
session's start (``session_started_unix_ns`` in ``case.json``), in the zone the reviewer asks
for (``--timezone``: an IANA name or UTC; default the machine's own), and which case it is: the
session's ``session_name`` (the name given at ``egosurg record start --case``; the case folder's
name when the session file is gone). A case that records no start (assembled by hand) shows
case time only.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from reconstructor.errors import CaseReplayError

_EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)


def pick_zone(name: str | None) -> dt.tzinfo:
    """The IANA zone ``name`` (``Europe/Berlin``), ``UTC``, or the machine's own zone."""
    if name is None:
        local = dt.datetime.now().astimezone().tzinfo
        return local if local is not None else dt.UTC
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise CaseReplayError(
            f"--timezone {name!r} is not a time zone: give an IANA name such as Europe/Berlin "
            "or UTC"
        ) from None


@dataclass(frozen=True)
class CaseClock:
    """Which case, and case time to time of day."""

    case_id: str
    started_unix_ns: int  # the session's start; 0: not recorded (a hand-made case)
    zone: dt.tzinfo = dt.UTC

    @classmethod
    def for_case(cls, folder: Path, zone: dt.tzinfo | None = None) -> CaseClock:
        from reconstructor.replay.session_check import case_session

        session = case_session(folder)
        zone = zone if zone is not None else pick_zone(None)
        if session is None:
            return cls(case_id=folder.resolve().name, started_unix_ns=0, zone=zone)
        return cls(
            case_id=session.name or folder.resolve().name,
            started_unix_ns=session.started_unix_ns,
            zone=zone,
        )

    @property
    def known(self) -> bool:
        return self.started_unix_ns > 0

    def at(self, t_s: float) -> dt.datetime:
        start = _EPOCH + dt.timedelta(microseconds=self.started_unix_ns // 1000)  # exact, no float
        return (start + dt.timedelta(seconds=float(t_s))).astimezone(self.zone)

    def time_of_day(self, t_s: float) -> str:
        """``09:00:07.250 UTC``: the wall-clock time of case time ``t_s`` and its zone; ""
        when the case records no start."""
        if not self.known:
            return ""
        when = self.at(t_s)
        ms = when.microsecond // 1000
        return f"{when.strftime('%H:%M:%S')}.{ms:03d} {when.tzname() or ''}".strip()

    def date(self, t_s: float) -> str:
        return self.at(t_s).strftime("%Y-%m-%d") if self.known else ""

    def stamp(self, t_s: float) -> str:
        """The line burned into a picture: ``2026-01-01 09:00:07.250 UTC  case <id>``."""
        if not self.known:
            return f"case {self.case_id} (start not recorded)"
        return f"{self.date(t_s)} {self.time_of_day(t_s)}  case {self.case_id}"


def add_time_of_day_axis(ax, clock: CaseClock) -> None:
    """A matplotlib axis along the top of ``ax`` (whose x is case time in seconds) that reads
    the time of day; nothing when the case records no start."""
    if not clock.known:
        return
    from matplotlib.ticker import FuncFormatter

    top = ax.secondary_xaxis("top")
    top.xaxis.set_major_formatter(FuncFormatter(lambda t, _: clock.time_of_day(t)[:12]))
    top.tick_params(labelsize=7)
    zone = clock.at(0.0).tzname() or ""
    top.set_xlabel(f"time of day ({zone}), case {clock.case_id}", fontsize=8)
