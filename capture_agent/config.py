"""``node.toml`` (one capture agent) and ``rig.toml`` (the recorder), as typed configs.

Example ``node.toml``::

    node_id = "orin-a"
    frames_bind = "tcp://10.10.0.11:5550"   # PUB: frames and 1 Hz status (the rig VLAN's address)
    control_bind = "tcp://10.10.0.11:5551"  # REP: status, heartbeat
    encoding = "jpeg"                  # or "raw_bgr8"
    jpeg_quality = 90

    [security]                         # CURVE keys (egosurg keys generate); paths relative to here
    secret_key = "/etc/egosurg/keys/orin-a.key_secret"     # this agent's keypair (mode 0600)
    allowed_keys = ["/etc/egosurg/keys/recorder.key", "/etc/egosurg/keys/operator.key"]
    # insecure = true                  # plaintext links: only for a bench, warns at every start
    # allow_all_interfaces = true      # allow binding tcp://* / 0.0.0.0

    [ptp]
    source = "pmc"                     # or "none" where there is no PTP (simulation)
    require_lock = true

    [[cameras]]
    source = "zed"                     # "zed", "sim" or "video"; the rest of the table is the
    serial = 41234567                  # source's own options (see capture_agent/sources/)

Example ``rig.toml``::

    rig_name = "or-3"
    fps = 30
    control_bind = "tcp://127.0.0.1:5560"
    output_dir = "/data/egosurg/sessions"
    require_ptp_lock = true
    receive_buffer_mb = 1024           # what queued frames may hold in the recorder, all agents
    # max_image_bytes = 6912000        # largest legal image (default: raw_bgr8 at HD1200)

    [security]
    secret_key = "/etc/egosurg/keys/recorder.key_secret"   # the recorder's keypair (mode 0600)
    # public_key = "/etc/egosurg/keys/recorder.key"        # default: secret_key minus _secret
    operator_keys = ["/etc/egosurg/keys/operator.key"]     # allowed on the control socket
    operator_key = "~/.egosurg/operator.key_secret"        # the key egosurg record/status use

    [[agents]]
    node_id = "orin-a"
    frames = "tcp://10.10.0.11:5550"
    control = "tcp://10.10.0.11:5551"
    cameras = [41234567, 41234568]     # expected serials; a start is refused if one is missing
    public_key = "/etc/egosurg/keys/orin-a.key"            # frames from another key are refused
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capture_agent.security import (
    LARGEST_IMAGE_BYTES,
    SECRET_SUFFIX,
    LinkSecurity,
    frame_message_max_bytes,
    key_path,
    secure_bind_check,
)
from protocol.errors import ConfigError
from protocol.messages import MAX_FRAME_BYTES

ENCODINGS = ("jpeg", "raw_bgr8")
MIN_RECEIVE_MESSAGES = 8  # the smallest receive queue per agent that receive_buffer_mb may give
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")


def load_toml(path: Path | str, what: str) -> tuple[dict[str, Any], str]:
    """(parsed table, raw text) of a TOML file, with clear errors."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise ConfigError(
            f"{what} {p} does not exist; see docs/capture.md for an example"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {p}: {exc.strerror}") from None
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p} is not valid TOML: {exc}") from None


class _Table:
    """Typed access to a TOML table whose errors name the file and the field."""

    def __init__(self, table: dict[str, Any], where: str) -> None:
        self.table = table
        self.where = where
        self.used: set[str] = set()

    def get(self, key: str, kind: type, default: Any = ..., *, check=None, hint: str = "") -> Any:
        self.used.add(key)
        if key not in self.table:
            if default is ...:
                raise ConfigError(f"{self.where}: '{key}' is required{'; ' + hint if hint else ''}")
            return default
        value = self.table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise ConfigError(
                f"{self.where}: '{key}' = {value!r} should be a {kind.__name__}"
                f"{'; ' + hint if hint else ''}"
            )
        if check is not None and not check(value):
            raise ConfigError(f"{self.where}: '{key}' = {value!r} is not allowed; {hint}")
        return value

    def reject_unknown(self, allowed_extra: tuple[str, ...] = ()) -> None:
        unknown = set(self.table) - self.used - set(allowed_extra)
        if unknown:
            raise ConfigError(
                f"{self.where}: unknown setting(s) {', '.join(sorted(unknown))}; check the spelling"
            )


def _endpoint(value: str) -> bool:
    return bool(re.match(r"^(tcp://[^:]+:\d{1,5}|ipc://.+|inproc://.+)$", value))


@dataclass(frozen=True, kw_only=True)
class CameraEntry:
    source: str
    table: dict[str, Any]
    where: str


_NO_KEYS = (
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
            raise ConfigError(f"{self.where or 'config'}: no CURVE keys; {_NO_KEYS}")
        return LinkSecurity.load(self.secret_key, self.allowed_keys)

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str, *, rig: bool) -> SecurityConfig:
        raw = data.get("security", {})
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: [security] must be a table")
        t = _Table(raw, f"{where} [security]")
        base = Path(where).parent
        insecure = t.get("insecure", bool, False)
        allowed_name = "operator_keys" if rig else "allowed_keys"
        allowed = t.get(allowed_name, list, [])
        if not all(isinstance(k, str) and k for k in allowed):
            raise ConfigError(f"{t.where}: '{allowed_name}' must list public key file paths")
        secret = t.get("secret_key", str, "")
        if not insecure and not secret:
            raise ConfigError(f"{t.where}: 'secret_key' is required; {_NO_KEYS}")
        if not insecure and not allowed:
            who = "the operators' public keys" if rig else "the recorder's and operators' keys"
            raise ConfigError(f"{t.where}: '{allowed_name}' must list {who}; {_NO_KEYS}")
        public = t.get("public_key", str, "") if rig else ""
        if rig and not public and secret.endswith(SECRET_SUFFIX):
            public = secret[: -len("_secret")]
        cfg = cls(
            insecure=insecure,
            allow_all_interfaces=t.get("allow_all_interfaces", bool, False),
            secret_key=key_path(secret, base) if secret else "",
            allowed_keys=tuple(key_path(k, base) for k in allowed),
            public_key=key_path(public, base) if public else "",
            operator_key=key_path(t.get("operator_key", str, ""), base) if rig else "",
            where=t.where,
        )
        t.reject_unknown()
        return cfg

    def check_bind(self, address: str, name: str) -> None:
        secure_bind_check(
            address, self.insecure, self.allow_all_interfaces, f"{self.where} ({name})"
        )


@dataclass(frozen=True, kw_only=True)
class NodeConfig:
    node_id: str
    frames_bind: str
    control_bind: str
    encoding: str = "jpeg"
    jpeg_quality: int = 90
    queue_frames: int = 120
    status_interval_s: float = 1.0
    watchdog_timeout_s: float = 2.0
    reopen_interval_s: float = 1.0
    ptp: dict[str, Any] = field(default_factory=dict)
    cameras: tuple[CameraEntry, ...] = ()
    security: SecurityConfig = SecurityConfig()
    source_path: str = ""

    @classmethod
    def from_toml(cls, path: Path | str) -> NodeConfig:
        data, _ = load_toml(path, "node config")
        return cls.from_table(data, str(path))

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str) -> NodeConfig:
        t = _Table(data, where)
        node_id = t.get("node_id", str, check=_NAME.match, hint="use letters, digits, - _ .")
        cams = data.get("cameras")
        t.used.add("cameras")
        if not isinstance(cams, list) or not cams:
            raise ConfigError(f"{where}: add at least one [[cameras]] table")
        entries = []
        for i, cam in enumerate(cams):
            cw = f"{where} [[cameras]] #{i + 1}"
            if not isinstance(cam, dict) or "source" not in cam:
                raise ConfigError(f'{cw}: needs source = "zed", "sim" or "video"')
            rest = {k: v for k, v in cam.items() if k != "source"}
            entries.append(CameraEntry(source=str(cam["source"]), table=rest, where=cw))
        ptp = data.get("ptp", {})
        t.used.add("ptp")
        if not isinstance(ptp, dict):
            raise ConfigError(f"{where}: [ptp] must be a table")
        cfg = cls(
            node_id=node_id,
            frames_bind=t.get(
                "frames_bind", str, check=_endpoint, hint="like tcp://10.10.0.11:5550"
            ),
            control_bind=t.get(
                "control_bind", str, check=_endpoint, hint="like tcp://10.10.0.11:5551"
            ),
            encoding=t.get(
                "encoding",
                str,
                "jpeg",
                check=lambda v: v in ENCODINGS,
                hint=f"one of {', '.join(ENCODINGS)}",
            ),
            jpeg_quality=t.get(
                "jpeg_quality", int, 90, check=lambda v: 1 <= v <= 100, hint="1 to 100"
            ),
            queue_frames=t.get(
                "queue_frames", int, 120, check=lambda v: 2 <= v <= 10_000, hint="2 to 10000"
            ),
            status_interval_s=t.get(
                "status_interval_s",
                float,
                1.0,
                check=lambda v: 0.05 <= v <= 60,
                hint="0.05 to 60 s",
            ),
            watchdog_timeout_s=t.get(
                "watchdog_timeout_s",
                float,
                2.0,
                check=lambda v: 0.1 <= v <= 600,
                hint="0.1 to 600 s",
            ),
            reopen_interval_s=t.get(
                "reopen_interval_s",
                float,
                1.0,
                check=lambda v: 0.05 <= v <= 600,
                hint="0.05 to 600 s",
            ),
            ptp=ptp,
            cameras=tuple(entries),
            source_path=where,
        )
        t.used.add("security")
        t.reject_unknown()
        security = SecurityConfig.from_table(data, where, rig=False)
        security.check_bind(cfg.frames_bind, "frames_bind")
        security.check_bind(cfg.control_bind, "control_bind")
        return dataclasses.replace(cfg, security=security)


@dataclass(frozen=True, kw_only=True)
class AgentEndpoint:
    node_id: str
    frames: str
    control: str
    cameras: tuple[int, ...] = ()
    public_key: str = ""  # the agent's public key file: the only key its frames may come from


@dataclass(frozen=True, kw_only=True)
class RigConfig:
    rig_name: str
    fps: float
    control_bind: str
    output_dir: str
    agents: tuple[AgentEndpoint, ...]
    require_ptp_lock: bool = True
    flush_interval_s: float = 0.5
    max_wait_ms: float = 500.0
    disk_reserve_gb: float = 2.0
    planned_duration_min: float = 60.0
    agent_timeout_s: float = 3.0
    receive_buffer_mb: float = 1024.0
    max_image_bytes: int = LARGEST_IMAGE_BYTES
    max_clock_skew_s: float = 10.0  # frames stamped further from the recorder's clock: refused
    security: SecurityConfig = SecurityConfig()
    toml_text: str = ""
    source_path: str = ""

    @property
    def expected_cameras(self) -> tuple[int, ...]:
        return tuple(s for a in self.agents for s in a.cameras)

    @classmethod
    def from_toml(cls, path: Path | str) -> RigConfig:
        data, text = load_toml(path, "rig config")
        return cls.from_table(data, str(path), text)

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str, text: str = "") -> RigConfig:
        t = _Table(data, where)
        agents_raw = data.get("agents")
        t.used.add("agents")
        if not isinstance(agents_raw, list) or not agents_raw:
            raise ConfigError(f"{where}: add one [[agents]] table per capture node")
        agents = []
        for i, a in enumerate(agents_raw):
            at = _Table(a if isinstance(a, dict) else {}, f"{where} [[agents]] #{i + 1}")
            cams = at.get("cameras", list, [])
            if not all(isinstance(c, int) and c > 0 for c in cams):
                raise ConfigError(f"{at.where}: 'cameras' must list camera serial numbers")
            agents.append(
                AgentEndpoint(
                    node_id=at.get("node_id", str, check=_NAME.match, hint="a node name"),
                    frames=at.get("frames", str, check=_endpoint, hint="like tcp://host:5550"),
                    control=at.get("control", str, check=_endpoint, hint="like tcp://host:5551"),
                    cameras=tuple(cams),
                    public_key=at.get("public_key", str, ""),
                )
            )
            at.reject_unknown()
        names = [a.node_id for a in agents]
        if len(set(names)) != len(names):
            raise ConfigError(f"{where}: two [[agents]] share a node_id; each node needs its own")
        serials = [s for a in agents for s in a.cameras]
        if len(set(serials)) != len(serials):
            raise ConfigError(f"{where}: a camera serial is listed under two agents")
        cfg = cls(
            rig_name=t.get("rig_name", str, "rig", check=_NAME.match, hint="a short name"),
            fps=t.get("fps", float, check=lambda v: 1 <= v <= 120, hint="1 to 120"),
            control_bind=t.get(
                "control_bind", str, check=_endpoint, hint="like tcp://127.0.0.1:5560"
            ),
            output_dir=t.get("output_dir", str, hint="where sessions are written"),
            agents=tuple(agents),
            require_ptp_lock=t.get("require_ptp_lock", bool, True),
            flush_interval_s=t.get(
                "flush_interval_s",
                float,
                0.5,
                check=lambda v: 0.01 <= v <= 1.0,
                hint="0.01 to 1 s (a crash loses at most this much)",
            ),
            max_wait_ms=t.get(
                "max_wait_ms",
                float,
                500.0,
                check=lambda v: 10 <= v <= 10_000,
                hint="10 to 10000 ms",
            ),
            disk_reserve_gb=t.get(
                "disk_reserve_gb",
                float,
                2.0,
                check=lambda v: v >= 0,
                hint="a non-negative size in GB",
            ),
            planned_duration_min=t.get(
                "planned_duration_min", float, 60.0, check=lambda v: v > 0, hint="minutes, > 0"
            ),
            agent_timeout_s=t.get(
                "agent_timeout_s", float, 3.0, check=lambda v: 0.5 <= v <= 60, hint="0.5 to 60 s"
            ),
            receive_buffer_mb=t.get(
                "receive_buffer_mb",
                float,
                1024.0,
                check=lambda v: 1 <= v <= 1_000_000,
                hint="MB of queued frames the recorder may hold, 1 to 1000000",
            ),
            max_image_bytes=t.get(
                "max_image_bytes",
                int,
                LARGEST_IMAGE_BYTES,
                check=lambda v: 1024 <= v <= MAX_FRAME_BYTES,
                hint=f"bytes per image, 1024 to {MAX_FRAME_BYTES}; larger images are refused",
            ),
            max_clock_skew_s=t.get(
                "max_clock_skew_s",
                float,
                10.0,
                check=lambda v: 0.1 <= v <= 86_400,
                hint="seconds a frame's capture time may differ from the recorder's clock, "
                "0.1 to 86400",
            ),
            toml_text=text,
            source_path=where,
        )
        t.used.add("security")
        t.reject_unknown()
        return _with_rig_security(cfg, data, where)


def _with_rig_security(cfg: RigConfig, data: dict[str, Any], where: str) -> RigConfig:
    security = SecurityConfig.from_table(data, where, rig=True)
    security.check_bind(cfg.control_bind, "control_bind")
    base = Path(where).parent
    agents = []
    for i, a in enumerate(cfg.agents):
        if not a.public_key and not security.insecure:
            raise ConfigError(
                f"{where} [[agents]] #{i + 1} ({a.node_id}): 'public_key' is required (the "
                f"agent's .key file); {_NO_KEYS}"
            )
        agents.append(
            dataclasses.replace(a, public_key=key_path(a.public_key, base) if a.public_key else "")
        )
    per_agent = cfg.receive_buffer_mb * 1e6 / len(agents)
    need = MIN_RECEIVE_MESSAGES * frame_message_max_bytes(cfg.max_image_bytes)
    if per_agent < need:
        raise ConfigError(
            f"{where}: receive_buffer_mb = {cfg.receive_buffer_mb:g} leaves {per_agent / 1e6:.0f} "
            f"MB per agent, under {MIN_RECEIVE_MESSAGES} of the largest legal frame messages "
            f"({need / 1e6:.0f} MB); raise receive_buffer_mb or lower max_image_bytes"
        )
    return dataclasses.replace(cfg, agents=tuple(agents), security=security)


def connect_address(bind: str) -> str:
    """The address a client on the same machine connects to for a bind address."""
    return bind.replace("tcp://*:", "tcp://127.0.0.1:").replace(
        "tcp://0.0.0.0:", "tcp://127.0.0.1:"
    )
