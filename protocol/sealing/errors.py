"""The errors of sealing: each is a ``UserError`` (one line, no traceback) that names the file,
the recipient or the payload concerned and what to do next."""

from __future__ import annotations

from protocol.errors import UserError


class IdentityError(UserError, ValueError):
    """An identity (secret key) or recipient (public key) file that cannot be used: missing,
    unreadable, readable by group or others, or not in the documented format."""


class WrongIdentityError(UserError, PermissionError):
    """No identity given opens the session's data key; the message names the session's
    recipients, so the user knows which identity file to fetch."""


class KeyBlockError(UserError, ValueError):
    """A session's key block that is not in the documented format (damaged or truncated)."""


class SealedPayloadError(UserError, ValueError):
    """A sealed payload that does not open where it is read: its bytes were changed, it was
    moved from another row, camera or session, or it is not a sealed payload at all. The
    message names the payload by session, field, camera, row, side and capture stamp."""


class IdentityRequiredError(UserError, PermissionError):
    """A sealed payload asked for without an identity: the message names the session's
    recipients (name and key id) and says how to give one (``--identity FILE`` or
    ``EGOSURG_IDENTITY``)."""
