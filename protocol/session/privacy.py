"""A session is a medical record: owner-only files and folders, and never a key in it.

Modes. The recorder's session folder is made ``0700`` and each session file is created ``0600``
(and the take journal beside them), set explicitly rather than left to the umask: a recorder
started by hand with the default umask 022 would otherwise write OR video that every account on
the workstation can read. The systemd units also set ``UMask=0077``; this does not rely on it.

Keys. ``rig.toml`` names CURVE key *files* in its ``[security]`` table; the session stores the
rig config's text (``rig_config_toml``) so a recording says how the rig was set up. A config
that holds a key inline instead must not carry it into a file that is copied to research
storage and kept for years, so ``redact_secrets`` removes, before the text is stored:

- the value of any key whose name says it is secret (``secret``, ``private``, ``password``,
  ``passphrase``, ``token``) unless the value is a file path;
- any string that is a CURVE key (40 Z85 characters), public or secret, whatever its key's name;
- any string holding a certificate or PEM block.

If the text still holds such a value after that (a multi-line string, say), or it is not valid
TOML, none of it is stored: a one-line note says why, and the recording goes on.
"""

from __future__ import annotations

import logging
import os
import re
import stat
from pathlib import Path
from typing import Any

from protocol.errors import ConfigError
from protocol.toml_config import parse_toml

logger = logging.getLogger(__name__)

FILE_MODE = 0o600
DIR_MODE = 0o700
REDACTED = "<removed: keys are never stored in a session>"

_SECRET_NAME = re.compile(r"secret|private|passw|passphrase|token", re.IGNORECASE)
_Z85 = "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#"
_Z85_KEY = re.compile("^[" + re.escape(_Z85) + "]{40}$")
_KEY_BLOCK = re.compile(r"-----BEGIN|secret-key\s*=", re.IGNORECASE)
# one-line TOML strings: "basic" (with escapes) and 'literal'
_STRING = re.compile(r'"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'')
_PAIR = re.compile(
    r"(?P<key>[A-Za-z0-9_-]+|\"[^\"\n]*\")\s*=\s*(?P<value>\"(?:[^\"\\\n]|\\.)*\"|'[^'\n]*')"
)


def create_private_file(path: Path) -> None:
    """Create ``path`` empty with mode 0600; ``FileExistsError`` if it exists (never replaced)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, FILE_MODE)
    try:
        os.fchmod(fd, FILE_MODE)  # the umask may have taken bits away; set exactly these
    finally:
        os.close(fd)


def make_private_dir(path: Path | str) -> Path:
    """Create ``path`` (and parents) if needed and make it 0700; logs when that changed it."""
    p = Path(path)
    p.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
    mode = stat.S_IMODE(p.stat().st_mode)
    if mode != DIR_MODE:
        os.chmod(p, DIR_MODE)
        logger.warning(
            "%s had mode %04o; made it %04o (owner only): sessions are medical records",
            p,
            mode,
            DIR_MODE,
        )
    return p


def _looks_like_path(value: str) -> bool:
    return (
        "\n" not in value
        and not _Z85_KEY.match(value)
        and ("/" in value or value.endswith((".key", ".key_secret")))
    )


def _is_secret(name: str, value: Any) -> bool:
    if isinstance(value, str):
        if value == REDACTED:
            return False
        if _Z85_KEY.match(value) or _KEY_BLOCK.search(value):
            return True
        return bool(_SECRET_NAME.search(name)) and bool(value) and not _looks_like_path(value)
    if isinstance(value, (list, tuple)):
        return any(_is_secret(name, v) for v in value)
    if isinstance(value, dict):
        return any(_is_secret(k, v) for k, v in value.items())
    return False


def _secret_names(table: dict[str, Any], where: str = "") -> list[str]:
    out = []
    for k, v in table.items():
        name = f"{where}.{k}" if where else k
        if isinstance(v, dict):
            out += _secret_names(v, name)
        elif _is_secret(k, v):
            out.append(name)
    return out


def _unquote(token: str) -> str:
    try:
        return str(parse_toml(f"v = {token}", "a value")["v"])
    except ConfigError:
        return token


def redact_secrets(text: str) -> str:
    """``text`` without key material (see the module docstring); unchanged when it has none."""
    if not text:
        return text
    try:
        names = _secret_names(parse_toml(text, "the rig config"))
    except ConfigError:
        logger.warning("the rig config is not valid TOML; it is not stored in the session")
        return "# the rig configuration was not stored: it is not valid TOML\n"
    if not names:
        return text
    quoted = f'"{REDACTED}"'

    def pair(m: re.Match[str]) -> str:
        key = m.group("key").strip('"')
        if _is_secret(key, _unquote(m.group("value"))):
            return m.group(0)[: m.start("value") - m.start(0)] + quoted
        return m.group(0)

    def string(m: re.Match[str]) -> str:
        return quoted if _is_secret("", _unquote(m.group(0))) else m.group(0)

    redacted = _STRING.sub(string, _PAIR.sub(pair, text))
    try:
        left = _secret_names(parse_toml(redacted, "the rig config"))
    except ConfigError:
        left = names
    if left:
        logger.warning(
            "the rig config holds key material inline (%s) that could not be removed; it is not "
            "stored in the session. Name key files in [security] instead",
            ", ".join(left),
        )
        return (
            "# the rig configuration was not stored: it holds key material inline "
            f"({', '.join(left)}); name key files in [security] instead\n"
        )
    logger.warning(
        "the rig config holds key material inline (%s); it is stored without it. Name key files "
        "in [security] instead",
        ", ".join(names),
    )
    return redacted
