"""The ``[security]`` table of node.toml and rig.toml: which key files a daemon uses, checked
when the config is read and loaded only when the daemon starts (``capture_agent/security.py``
does the loading and the CURVE setup: ``LinkSecurity.from_config``; docs/capture.md,
"Security", is the operator's guide).

A node's table lists the keys allowed to connect (``allowed_keys``: the recorder's and the
operators'); a rig's lists the operators allowed on the control socket (``operator_keys``), the
recorder's public key clients connect to, and the key ``egosurg record``/``status`` use. Key paths
are kept as written; ``resolved`` makes the relative ones relative to the config's folder. The key
files' names (``PUBLIC_SUFFIX``, ``SECRET_SUFFIX``) and the rule against binding every interface
live here too: they are what a config may say, and the simulator's deploy writes such configs.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from protocol.config_fields import internal, validate
from protocol.errors import ConfigError

# pyzmq's certificate files (egosurg keys generate): NAME.key holds the public key, NAME.key_secret
# both; only the secret file is private
PUBLIC_SUFFIX = ".key"
SECRET_SUFFIX = ".key_secret"
_S = TypeVar("_S", bound="SecurityConfig")
NO_KEYS = (
    "make keys with 'egosurg keys generate --out DIR --name NAME' and name them in [security] "
    "(see docs/capture.md, Security), or set insecure = true in [security] for plaintext links"
)


@dataclass(frozen=True, kw_only=True)
class SecurityConfig:
    """What node.toml's and rig.toml's ``[security]`` share: key file paths, not keys (a client
    reading rig.toml need not be able to read the recorder's secret key).
    ``LinkSecurity.from_config`` (capture_agent/security.py) loads them when a daemon starts."""

    insecure: bool = False  # plaintext links: only for a bench, warns at every start
    allow_all_interfaces: bool = False  # allow binding tcp://* / 0.0.0.0
    secret_key: str = ""  # this daemon's keypair (a .key_secret file, mode 0600)
    where: str = internal("")  # the config file's [security], for errors

    def __post_init__(self) -> None:
        validate(self)

    @property
    def peer_keys(self) -> tuple[str, ...]:
        """The public key files allowed to connect to this daemon."""
        return ()

    def require_keys(self) -> None:
        """Refuse a table that names no keys and does not say ``insecure = true`` (the node and
        rig configs ask last, so a file's other mistakes are named first)."""
        if not self.insecure and not self.secret_key:
            raise ConfigError(f"[security]: 'secret_key' is required; {NO_KEYS}")

    def check_bind(self, address: str, name: str) -> None:
        where = f"{self.where} ({name})" if self.where else name
        secure_bind_check(address, self.insecure, self.allow_all_interfaces, where)

    def resolved(self: _S, config_path: str) -> _S:
        """Key paths relative to the folder of ``config_path`` made whole; ``where`` set."""
        base = Path(config_path).parent
        paths: dict[str, Any] = {
            f.name: _paths(getattr(self, f.name), base)
            for f in dataclasses.fields(self)
            if f.name.endswith(("_key", "_keys"))
        }
        return dataclasses.replace(self, **paths, where=f"{config_path} [security]")


def _paths(value: str | tuple[str, ...], base: Path) -> str | tuple[str, ...]:
    if isinstance(value, tuple):
        return tuple(key_path(v, base) for v in value)
    return key_path(value, base) if value else ""


@dataclass(frozen=True, kw_only=True)
class NodeSecurityConfig(SecurityConfig):
    """node.toml's ``[security]``."""

    allowed_keys: tuple[str, ...] = ()  # the recorder's and the operators' public keys

    def require_keys(self) -> None:
        super().require_keys()
        if not self.insecure and not self.allowed_keys:
            raise ConfigError(
                f"[security]: 'allowed_keys' must list the recorder's and operators' keys; "
                f"{NO_KEYS}"
            )

    @property
    def peer_keys(self) -> tuple[str, ...]:
        return self.allowed_keys


@dataclass(frozen=True, kw_only=True)
class RigSecurityConfig(SecurityConfig):
    """rig.toml's ``[security]``."""

    operator_keys: tuple[str, ...] = ()  # allowed on the control socket
    public_key: str = ""  # the recorder's public key; default: secret_key minus _secret
    operator_key: str = ""  # the keypair that egosurg record/status/shell use

    def require_keys(self) -> None:
        super().require_keys()
        if not self.insecure and not self.operator_keys:
            raise ConfigError(
                f"[security]: 'operator_keys' must list the operators' public keys; {NO_KEYS}"
            )

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.public_key and self.secret_key.endswith(SECRET_SUFFIX):
            object.__setattr__(self, "public_key", self.secret_key[: -len("_secret")])

    @property
    def peer_keys(self) -> tuple[str, ...]:
        return self.operator_keys


def secure_bind_check(address: str, links_insecure: bool, allow_all: bool, where: str) -> None:
    """Refuse a bind on every interface unless the config says so out loud."""
    host = address.split("://", 1)[-1].rsplit(":", 1)[0]
    if host in ("*", "0.0.0.0", "[::]", "::") and not (links_insecure or allow_all):
        raise ConfigError(
            f"{where}: binding {address} listens on every interface; bind the rig network's "
            "address (e.g. tcp://10.10.0.11:5550), or set allow_all_interfaces = true in "
            "[security]"
        )


def key_path(value: str, base_dir: Path) -> str:
    """A key file path from a config: relative paths are relative to the config's folder."""
    p = Path(os.path.expanduser(value))
    return str(p if p.is_absolute() else base_dir / p)
