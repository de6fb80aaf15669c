"""The simulator's errors: each one a ``UserError`` (the ``egosurg`` command prints it as one line,
no traceback) and the builtin it is most like, so callers can catch either.
"""

from __future__ import annotations

from protocol.errors import UserError


class UnknownPhaseError(UserError, ValueError):
    """A workflow phase the simulator does not know; the message lists the ones it does."""


class OutsideRoomError(UserError, ValueError):
    """A camera or object placed outside the room."""


class SimTimeError(UserError, ValueError):
    """A time that the simulation cannot show."""


class SimRigError(UserError, RuntimeError):
    """A simulated rig that cannot be deployed or run; the message says what to check."""
