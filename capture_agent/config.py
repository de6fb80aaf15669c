"""``node.toml`` (one capture agent) and ``rig.toml`` (the recorder), as typed configs.

Example ``node.toml``::

    node_id = "orin-a"
    frames_bind = "tcp://*:5550"       # PUB: frames and 1 Hz status
    control_bind = "tcp://*:5551"      # REP: status, heartbeat
    encoding = "jpeg"                  # or "raw_bgr8"
    jpeg_quality = 90

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

    [[agents]]
    node_id = "orin-a"
    frames = "tcp://10.10.0.11:5550"
    control = "tcp://10.10.0.11:5551"
    cameras = [41234567, 41234568]     # expected serials; a start is refused if one is missing
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.errors import ConfigError

ENCODINGS = ("jpeg", "raw_bgr8")
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
            frames_bind=t.get("frames_bind", str, check=_endpoint, hint="like tcp://*:5550"),
            control_bind=t.get("control_bind", str, check=_endpoint, hint="like tcp://*:5551"),
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
        t.reject_unknown()
        return cfg


@dataclass(frozen=True, kw_only=True)
class AgentEndpoint:
    node_id: str
    frames: str
    control: str
    cameras: tuple[int, ...] = ()


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
            toml_text=text,
            source_path=where,
        )
        t.reject_unknown()
        return cfg


def connect_address(bind: str) -> str:
    """The address a client on the same machine connects to for a bind address."""
    return bind.replace("tcp://*:", "tcp://127.0.0.1:").replace(
        "tcp://0.0.0.0:", "tcp://127.0.0.1:"
    )
