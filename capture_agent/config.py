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
    write_queue_mb = 256               # frames waiting for the disk (a stall): ~3 s of the rig
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

from capture_agent.security import LARGEST_IMAGE_BYTES, frame_message_max_bytes, key_path
from capture_agent.security_config import NO_KEYS, SecurityConfig
from capture_agent.toml_table import TableReader, load_toml
from protocol.errors import ConfigError
from protocol.wire import MAX_FRAME_BYTES

__all__ = [
    "ENCODINGS",
    "MIN_RECEIVE_MESSAGES",
    "AgentEndpoint",
    "CameraEntry",
    "EncodingName",
    "NodeConfig",
    "RigConfig",
    "SecurityConfig",
    "connect_address",
    "load_toml",
]

# The names of protocol.wire.Encoding, as node.toml spells them.
EncodingName = Literal["jpeg", "raw_bgr8"]
ENCODINGS: tuple[EncodingName, ...] = get_args(EncodingName)
MIN_RECEIVE_MESSAGES = 8  # the smallest receive queue per agent that receive_buffer_mb may give
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")
_NAME_HINT = "a name of letters, digits, - _ . (at most 32)"


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
    encoding: EncodingName = "jpeg"
    jpeg_quality: int = 90
    queue_frames: int = 120
    status_interval_s: float = 1.0
    watchdog_timeout_s: float = 2.0
    reopen_interval_s: float = 1.0
    ptp: dict[str, Any] = field(default_factory=dict)
    cameras: tuple[CameraEntry, ...] = ()
    security: SecurityConfig = field(default_factory=SecurityConfig)
    source_path: str = ""

    @classmethod
    def from_toml(cls, path: Path | str) -> NodeConfig:
        data, _ = load_toml(path, "node config")
        return cls.from_table(data, str(path))

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str) -> NodeConfig:
        t = TableReader(data, where)
        node_id = t.text("node_id", check=_NAME.match, hint=_NAME_HINT)
        cams = data.get("cameras")
        t.skip("cameras", "security")
        if not isinstance(cams, list) or not cams:
            raise ConfigError(f"{where}: add at least one [[cameras]] table")
        entries = []
        for i, cam in enumerate(cams):
            cw = f"{where} [[cameras]] #{i + 1}"
            if not isinstance(cam, dict) or "source" not in cam:
                raise ConfigError(f'{cw}: needs source = "zed", "sim" or "video"')
            rest = {k: v for k, v in cam.items() if k != "source"}
            entries.append(CameraEntry(source=str(cam["source"]), table=rest, where=cw))
        cfg = cls(
            node_id=node_id,
            frames_bind=t.text(
                "frames_bind", check=_endpoint, hint="an endpoint like tcp://10.10.0.11:5550"
            ),
            control_bind=t.text(
                "control_bind", check=_endpoint, hint="an endpoint like tcp://10.10.0.11:5551"
            ),
            encoding=t.choice("encoding", ENCODINGS, "jpeg"),
            jpeg_quality=t.integer(
                "jpeg_quality", 90, check=lambda v: 1 <= v <= 100, hint="an integer, 1 to 100"
            ),
            queue_frames=t.integer(
                "queue_frames",
                120,
                check=lambda v: 2 <= v <= 10_000,
                hint="an integer, 2 to 10000",
            ),
            status_interval_s=t.number(
                "status_interval_s", 1.0, check=lambda v: 0.05 <= v <= 60, hint="0.05 to 60 s"
            ),
            watchdog_timeout_s=t.number(
                "watchdog_timeout_s", 2.0, check=lambda v: 0.1 <= v <= 600, hint="0.1 to 600 s"
            ),
            reopen_interval_s=t.number(
                "reopen_interval_s", 1.0, check=lambda v: 0.05 <= v <= 600, hint="0.05 to 600 s"
            ),
            ptp=t.table_of("ptp"),
            cameras=tuple(entries),
            source_path=where,
        )
        t.finish()
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
    # 0.2 s: capture-to-durable p99 under 250 ms at the full rig for about 1-2 % of a core more
    # than 0.5 s (BENCHMARKS.md); a crash loses at most this much
    flush_interval_s: float = 0.2
    max_wait_ms: float = 500.0
    disk_reserve_gb: float = 2.0
    planned_duration_min: float = 60.0
    agent_timeout_s: float = 3.0
    receive_buffer_mb: float = 1024.0
    # frames received but not yet written (a stalling disk); ~3.5 s of the reference rig's
    # 4 x HD1200 JPEG streams (~75 MB/s); at least one largest legal frame message
    write_queue_mb: float = 256.0
    max_image_bytes: int = LARGEST_IMAGE_BYTES
    max_clock_skew_s: float = 10.0  # frames stamped further from the recorder's clock: refused
    security: SecurityConfig = field(default_factory=SecurityConfig)
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
        t = TableReader(data, where)
        agents_raw = data.get("agents")
        t.skip("agents", "security")
        if not isinstance(agents_raw, list) or not agents_raw:
            raise ConfigError(f"{where}: add one [[agents]] table per capture node")
        agents = tuple(_agent(a, f"{where} [[agents]] #{i + 1}") for i, a in enumerate(agents_raw))
        names = [a.node_id for a in agents]
        if len(set(names)) != len(names):
            raise ConfigError(f"{where}: two [[agents]] share a node_id; each node needs its own")
        serials = [s for a in agents for s in a.cameras]
        if len(set(serials)) != len(serials):
            raise ConfigError(f"{where}: a camera serial is listed under two agents")
        cfg = cls(
            rig_name=t.text("rig_name", "rig", check=_NAME.match, hint=_NAME_HINT),
            fps=t.number("fps", check=lambda v: 1 <= v <= 120, hint="a number, 1 to 120"),
            control_bind=t.text(
                "control_bind", check=_endpoint, hint="an endpoint like tcp://127.0.0.1:5560"
            ),
            output_dir=t.text("output_dir", hint="the folder sessions are written to"),
            agents=agents,
            require_ptp_lock=t.boolean("require_ptp_lock", True),
            flush_interval_s=t.number(
                "flush_interval_s",
                0.2,
                check=lambda v: 0.01 <= v <= 1.0,
                hint="0.01 to 1 s (a crash loses at most this much)",
            ),
            max_wait_ms=t.number(
                "max_wait_ms", 500.0, check=lambda v: 10 <= v <= 10_000, hint="10 to 10000 ms"
            ),
            disk_reserve_gb=t.number(
                "disk_reserve_gb", 2.0, check=lambda v: v >= 0, hint="a non-negative size in GB"
            ),
            planned_duration_min=t.number(
                "planned_duration_min", 60.0, check=lambda v: v > 0, hint="minutes, > 0"
            ),
            agent_timeout_s=t.number(
                "agent_timeout_s", 3.0, check=lambda v: 0.5 <= v <= 60, hint="0.5 to 60 s"
            ),
            receive_buffer_mb=t.number(
                "receive_buffer_mb",
                1024.0,
                check=lambda v: 1 <= v <= 1_000_000,
                hint="the MB of queued frames the recorder may hold, 1 to 1000000",
            ),
            write_queue_mb=t.number(
                "write_queue_mb",
                256.0,
                check=lambda v: 1 <= v <= 1_000_000,
                hint="the MB of frames waiting for the disk the recorder may hold, 1 to 1000000",
            ),
            max_image_bytes=t.integer(
                "max_image_bytes",
                LARGEST_IMAGE_BYTES,
                check=lambda v: 1024 <= v <= MAX_FRAME_BYTES,
                hint=f"bytes per image, 1024 to {MAX_FRAME_BYTES}; larger images are refused",
            ),
            max_clock_skew_s=t.number(
                "max_clock_skew_s",
                10.0,
                check=lambda v: 0.1 <= v <= 86_400,
                hint="the seconds a frame's capture time may differ from the recorder's clock, "
                "0.1 to 86400",
            ),
            toml_text=text,
            source_path=where,
        )
        t.finish()
        return _with_rig_security(cfg, data, where)


def _agent(table: object, where: str) -> AgentEndpoint:
    # a non-table entry reads as an empty one, so the error names its first required field
    at = TableReader(table if isinstance(table, dict) else {}, where)
    agent = AgentEndpoint(
        node_id=at.text("node_id", check=_NAME.match, hint=_NAME_HINT),
        frames=at.text("frames", check=_endpoint, hint="an endpoint like tcp://host:5550"),
        control=at.text("control", check=_endpoint, hint="an endpoint like tcp://host:5551"),
        cameras=tuple(at.integers("cameras", [], hint="a list of camera serial numbers")),
        public_key=at.text("public_key", "", hint="the agent's public key file path"),
    )
    at.finish()
    return agent


def _with_rig_security(cfg: RigConfig, data: dict[str, Any], where: str) -> RigConfig:
    security = SecurityConfig.from_table(data, where, rig=True)
    security.check_bind(cfg.control_bind, "control_bind")
    base = Path(where).parent
    agents = []
    for i, a in enumerate(cfg.agents):
        if not a.public_key and not security.insecure:
            raise ConfigError(
                f"{where} [[agents]] #{i + 1} ({a.node_id}): 'public_key' is required (the "
                f"agent's .key file); {NO_KEYS}"
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
    if cfg.write_queue_mb * 1e6 < frame_message_max_bytes(cfg.max_image_bytes):
        raise ConfigError(
            f"{where}: write_queue_mb = {cfg.write_queue_mb:g} cannot hold one largest legal "
            f"frame message ({frame_message_max_bytes(cfg.max_image_bytes) / 1e6:.0f} MB); "
            "raise write_queue_mb or lower max_image_bytes"
        )
    return dataclasses.replace(cfg, agents=tuple(agents), security=security)


def connect_address(bind: str) -> str:
    """The address a client on the same machine connects to for a bind address."""
    return bind.replace("tcp://*:", "tcp://127.0.0.1:").replace(
        "tcp://0.0.0.0:", "tcp://127.0.0.1:"
    )
