"""The calibration's user errors: each message names what is wrong (the camera, the setting, the
file) and what to do, so ``egosurg calibrate`` prints it as one line and exits."""

from __future__ import annotations

from protocol.errors import UserError


class ExtractionError(UserError, ValueError):
    """A wand session (or an extraction setting) the observations cannot be taken from."""


class SolveError(UserError, ValueError):
    """Wand data the rig cannot be solved from; the message names the camera and what to do."""
