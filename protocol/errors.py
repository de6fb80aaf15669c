"""The base of every error a user can cause.

Domain errors subclass the matching builtin *and* ``UserError``, for example
``class ConfFormatError(UserError, ValueError)``. The ``egosurg`` command prints a ``UserError`` as
one line that says what is wrong and what to do, with no traceback; anything else is a bug and keeps
its traceback.
"""


class UserError(Exception):
    """Raised for bad input or a bad environment; the message tells the user what to do."""


class ConfigError(UserError, ValueError):
    """A configuration file or option that cannot be used; the message names the file and field."""
