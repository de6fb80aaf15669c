"""The capture side's errors. A ``UserError`` (the ``egosurg`` command prints it as one line, no
traceback) is also the builtin it is most like, so callers can catch either; the camera seam's
two errors are plain ``RuntimeError``: the agent catches them and reopens the camera.
"""

from __future__ import annotations

from protocol.errors import UserError


class CameraUnavailableError(RuntimeError):
    """The camera is missing or vanished (unplugged, rebooting): close it and reopen it later."""


class EndOfRecordingError(CameraUnavailableError):
    """A finite source (a video file without ``loop``) has no more frames."""


class SdkMissingError(UserError, ImportError):
    """The ZED SDK's Python API (pyzed) cannot be imported; the message says what to install."""


class Refused(UserError, RuntimeError):
    """A request that cannot be done now; the message says why and what to do."""


class SyncError(UserError, ValueError):
    """A frame the synchroniser cannot take, e.g. from a camera that is not in the rig."""


class RecorderUnreachableError(UserError, ConnectionError):
    """No recorder answers at the control address; the message names it and what to check."""


class CommandRefusedError(UserError, RuntimeError):
    """The recorder answered, and said no; the message is its reason."""


class ConsoleError(UserError, OSError):
    """Something the console could not do on this computer (e.g. write a picture)."""


class KeyFileError(UserError, FileExistsError):
    """A key file that would be overwritten."""
