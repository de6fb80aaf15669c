"""The recorder's recipients: rig.toml's ``[sealing]`` files, loaded and checked once, when the
recorder starts, so a missing or damaged key stops the start in one line instead of a take.

Only public keys are accepted: a file holding a secret identity is refused even though its
public half would do, because a recorder with an identity could open what it wrote (the OR
workstation is the machine most likely to be stolen). ``plaintext = true`` is logged as a
warning at every start, as plaintext links are.
"""

from __future__ import annotations

import logging
from pathlib import Path

from protocol.errors import ConfigError
from protocol.formats.sealing_config import RigSealingConfig
from protocol.sealing import IdentityError, Recipient, load_recipient
from protocol.sealing.keyfiles import IDENTITY_HEADER

log = logging.getLogger(__name__)


def load_recipients(config: RigSealingConfig, who: str) -> tuple[Recipient, ...]:
    """The recipients sessions are sealed for (empty with ``plaintext = true``, warned)."""
    if config.plaintext:
        warn_plaintext(who)
        return ()
    recipients: list[Recipient] = []
    for path in config.recipients:
        recipient = _public_only(Path(path), config.where)
        same = [r for r in recipients if r.key_id == recipient.key_id]
        if same:
            raise ConfigError(
                f"{config.where}: {path} holds the same key as {same[0].label()}; each "
                "recipient must be a different key"
            )
        recipients.append(recipient)
    log.info("%s: sessions sealed for %s", who, ", ".join(r.label() for r in recipients))
    return tuple(recipients)


def _public_only(path: Path, where: str) -> Recipient:
    try:
        recipient = load_recipient(path)
        text = path.read_text(encoding="utf-8")
    except IdentityError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if any(line.strip() == IDENTITY_HEADER for line in text.splitlines()):
        raise ConfigError(
            f"{where}: {path} is a secret identity, which opens every session sealed for "
            f"{recipient.name}; name the public {recipient.name}.recipient file instead and "
            "move the identity off this recorder"
        )
    return recipient


def warn_plaintext(who: str) -> None:
    """Logged at every start of a recorder whose sessions are not sealed."""
    log.warning(
        "%s: PLAINTEXT sessions (plaintext = true in [sealing]): patient video is stored "
        "unencrypted, readable by anyone with the disk or a backup. Make a site key with "
        "'egosurg keys generate --kind site' and name its .recipient in [sealing]",
        who,
    )
