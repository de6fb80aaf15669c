"""The simulator's errors: each one a ``UserError`` (the ``egosurg`` command prints it as one line,
no traceback) and the builtin it is most like, so callers can catch either.
"""

from __future__ import annotations

from protocol.errors import UserError


class UnknownPhaseError(UserError, ValueError):
    pass


class OutsideRoomError(UserError, ValueError):
    """A camera or object placed outside the room."""


class SimTimeError(UserError, ValueError):
    """A time that the simulation cannot show."""


class SimRigError(UserError, RuntimeError):
    pass
