"""The ``[security]`` table of node.toml and rig.toml: which key files a daemon uses, checked
when the config is read and loaded only when the daemon starts (``capture_agent/security.py``
does the loading and the CURVE setup; docs/capture.md, "Security", is the operator's guide)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capture_agent.security import SECRET_SUFFIX, LinkSecurity, key_path, secure_bind_check
from capture_agent.toml_table import TableReader
from protocol.errors import ConfigError

NO_KEYS = (
    "make keys with 'egosurg keys generate --out DIR --name NAME' and name them in [security] "
    "(see docs/capture.md, Security), or set insecure = true in [security] for plaintext links"
)


@dataclass(frozen=True, kw_only=True)
class SecurityConfig:
    """The ``[security]`` table of node.toml or rig.toml: key file paths (relative paths are
    relative to the config's folder), not keys: a client reading rig.toml need not be able to
    read the recorder's secret key. ``links()`` loads them when a daemon starts."""

    insecure: bool = False
    allow_all_interfaces: bool = False
    secret_key: str = ""  # this daemon's keypair (a .key_secret file, mode 0600)
    allowed_keys: tuple[str, ...] = ()  # node: recorder + operators; rig: operators on control
    public_key: str = ""  # rig: the recorder's public key, which clients connect to
    operator_key: str = ""  # rig: the keypair that egosurg record/status/shell use
    where: str = ""

    def links(self) -> LinkSecurity:
        """This daemon's keys, loaded (ConfigError when missing, unreadable or not 0600)."""
        if self.insecure:
            return LinkSecurity.plaintext()
        if not self.secret_key or not self.allowed_keys:
            raise ConfigError(f"{self.where or 'config'}: no CURVE keys; {NO_KEYS}")
        return LinkSecurity.load(self.secret_key, self.allowed_keys)

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str, *, rig: bool) -> SecurityConfig:
        raw = data.get("security", {})
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: [security] must be a table")
        t = TableReader(raw, f"{where} [security]")
        base = Path(where).parent
        insecure = t.boolean("insecure", False)
        allowed_name = "operator_keys" if rig else "allowed_keys"
        allowed = t.texts(allowed_name, [], hint="a list of public key file paths")
        secret = t.text("secret_key", "", hint="a secret key file path")
        if not insecure and not secret:
            raise ConfigError(f"{t.where}: 'secret_key' is required; {NO_KEYS}")
        if not insecure and not allowed:
            who = "the operators' public keys" if rig else "the recorder's and operators' keys"
            raise ConfigError(f"{t.where}: '{allowed_name}' must list {who}; {NO_KEYS}")
        public = t.text("public_key", "", hint="a public key file path") if rig else ""
        if rig and not public and secret.endswith(SECRET_SUFFIX):
            public = secret[: -len("_secret")]
        operator = t.text("operator_key", "", hint="a secret key file path") if rig else ""
        cfg = cls(
            insecure=insecure,
            allow_all_interfaces=t.boolean("allow_all_interfaces", False),
            secret_key=key_path(secret, base) if secret else "",
            allowed_keys=tuple(key_path(k, base) for k in allowed),
            public_key=key_path(public, base) if public else "",
            operator_key=key_path(operator, base) if operator else "",
            where=t.where,
        )
        t.finish()
        return cfg

    def check_bind(self, address: str, name: str) -> None:
        secure_bind_check(
            address, self.insecure, self.allow_all_interfaces, f"{self.where} ({name})"
        )
