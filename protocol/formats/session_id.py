"""The session a review file was made for: its ``[session]`` table.

A roles or trajectory file (``egosurg-trajectories``) and a site or field file
(``egosurg-site``) describe one recording: a role's eye at case time 7 s means nothing in
another session, whose 7 s is another moment (or another room). So the writers that know the
session (``egosurg sim roles``, ``egosurg sim contact``) record it, and the review commands
compare it with the case's session and refuse a file made for another one::

    [session]                              # the session this file was made for
    name = "sim-intraoperative-seed3"      # the session file's session_name
    started_unix_ns = 1767225600000000000  # its started_unix_ns: 2026-01-01 00:00:00.000 UTC

Both values are the session file's own root attributes (docs/session.md): the name alone
repeats (a rig names sessions by room and date, a resumed take keeps its name), the start
alone can too (the simulator starts every evaluation session at its epoch), together they do
not. A file without the table (written by hand, or before the table existed) is still read;
the commands say in one line that they could not check it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from protocol.errors import UserError


class SessionMismatchError(UserError, ValueError):
    """A review file made for another session than the case's; the message names both."""


@dataclass(frozen=True, kw_only=True)
class SessionId:
    name: str  # the session's session_name ("" when unknown: a case whose session file is gone)
    started_unix_ns: int

    def __post_init__(self) -> None:
        if not isinstance(self.started_unix_ns, int) or self.started_unix_ns <= 0:
            raise ValueError(
                f"started_unix_ns {self.started_unix_ns!r} must be the session's start, a "
                "positive whole number of nanoseconds since 1970 (the session file's attribute)"
            )

    @property
    def started_utc(self) -> str:
        ns = self.started_unix_ns
        day_time = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns // 1_000_000_000))
        return f"{day_time}.{ns // 1_000_000 % 1000:03d} UTC"

    def describe(self) -> str:
        """``session 'x' started 2026-01-01 00:00:00.000 UTC``: how a message names it."""
        name = f"session {self.name!r}" if self.name else "a session"
        return f"{name} started {self.started_utc}"

    def same_as(self, other: SessionId) -> bool:
        """The same recording: the same start, and the same name where both are known."""
        if self.started_unix_ns != other.started_unix_ns:
            return False
        return not (self.name and other.name) or self.name == other.name


def session_toml_lines(session: SessionId | None) -> list[str]:
    """The ``[session]`` table's lines (none for ``None``); a writer puts them after its
    top-level keys."""
    if session is None:
        return []
    return [
        "",
        "[session]  # the session this file was made for: review commands check it",
        f"name = {_toml_string(session.name)}",
        f"started_unix_ns = {session.started_unix_ns}  # {session.started_utc}",
    ]


def _toml_string(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + "".join(c if c.isprintable() else f"\\u{ord(c):04x}" for c in escaped) + '"'


def check_made_for(
    made_for: SessionId | None, case_session: SessionId, *, what: str, case: str
) -> str | None:
    """Refuse (``SessionMismatchError``) ``what`` (a file, as the user named it) made for
    another session than ``case``'s; the warning line to show when it names no session."""
    if made_for is None:
        return (
            f"{what} does not say which session it was made for, so it cannot be checked "
            f"against {case} ({case_session.describe()}); make sure it belongs to that session"
        )
    if not made_for.same_as(case_session):
        raise SessionMismatchError(
            f"{what} was made for {made_for.describe()}, but {case} is of "
            f"{case_session.describe()}: give the file made for this case's session "
            "(egosurg sim roles SESSION.h5 writes the sim's)"
        )
    return None
