"""rig.toml's ``[sealing]`` table: whom the recorder seals its sessions for.

A session is sealed for one or more recipients (``protocol/sealing``): their public keys, in
``NAME.recipient`` files made by ``egosurg keys generate --kind site``. The recorder holds only
these public files, so nothing on it opens what it wrote; the matching ``NAME.identity`` files
stay where sessions are read. Two recipients are recommended (one kept offline): a session whose
every recipient identity is lost cannot be opened by anyone.

Example::

    [sealing]
    recipients = [
        "/etc/egosurg/keys/site.recipient",     # the reconstruction workstation
        "/etc/egosurg/keys/escrow.recipient",   # kept offline
    ]

or, for a bench without patient video only, ``plaintext = true`` (warned at every start). A
table that says neither is refused when rig.toml is read. Paths are kept as written;
``resolved`` makes the relative ones relative to rig.toml's folder. The files themselves are
read when the recorder starts (``capture_agent/recorder/sealing.py``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from protocol.config_fields import internal, option, validate
from protocol.errors import ConfigError
from protocol.formats.security_config import key_path

MAX_RECIPIENTS = 16  # a session's key block holds at most 16 wraps (protocol/sealing)
RECIPIENT_SUFFIX = ".recipient"  # protocol.sealing's; kept here so config reading needs no crypto
IDENTITY_SUFFIX = ".identity"
NO_RECIPIENTS = (
    "[sealing]: name the public keys sessions are sealed for: make a key pair on the "
    "workstation that reads sessions ('egosurg keys generate --kind site --name NAME --out "
    "DIR'), copy only NAME.recipient to this recorder and set recipients = "
    '["/etc/egosurg/keys/NAME.recipient"] in [sealing] (two recommended, see docs/capture.md, '
    '"Sealed sessions"); or set plaintext = true in [sealing] for unencrypted sessions'
)


def _recipient_files(paths: tuple[str, ...]) -> bool:
    return len(paths) <= MAX_RECIPIENTS and all(
        p.strip() and not p.endswith(IDENTITY_SUFFIX) for p in paths
    )


@dataclass(frozen=True, kw_only=True)
class RigSealingConfig:
    """rig.toml's ``[sealing]``: recipient file paths (not keys), checked when rig.toml is
    read and loaded when the recorder starts."""

    recipients: tuple[str, ...] = option(
        (),
        test=_recipient_files,
        must=(
            f"must list 1 to {MAX_RECIPIENTS} public {RECIPIENT_SUFFIX} files; an "
            f"{IDENTITY_SUFFIX} file is a secret key and never belongs on a recorder"
        ),
    )
    # unencrypted sessions: only for a bench without patient video; warned at every start
    plaintext: bool = False
    where: str = internal("")  # the config file's [sealing], for errors

    def __post_init__(self) -> None:
        validate(self)
        if len(set(self.recipients)) != len(self.recipients):
            raise ConfigError(f"{self.where or '[sealing]'}: a recipient file is listed twice")

    def require_choice(self) -> None:
        """Refuse a table that names no recipients and does not say ``plaintext = true``, or
        says both (rig.toml asks last, so a file's other mistakes are named first)."""
        if self.plaintext and self.recipients:
            raise ConfigError(
                "[sealing]: 'recipients' and plaintext = true contradict each other; remove "
                "plaintext = true to seal sessions for the recipients"
            )
        if not self.plaintext and not self.recipients:
            raise ConfigError(NO_RECIPIENTS)

    def resolved(self, config_path: str) -> RigSealingConfig:
        """Recipient paths relative to the folder of ``config_path`` made whole; ``where`` set."""
        folder = Path(config_path).parent
        return dataclasses.replace(
            self,
            recipients=tuple(key_path(p, folder) for p in self.recipients),
            where=f"{config_path} [sealing]",
        )
