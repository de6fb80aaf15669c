"""``rig.toml``: the recorder's config, typed, with the capture nodes it records from.

Every option's range or rule is stated once, on its field; a config checks itself when it is made
(``protocol/config_fields.py``), from a file (``protocol/toml_config.py``: an unknown key or a bad
value fails at load, in one line naming the file, the table and the field) or in code.

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

    [sealing]                          # sessions encrypted for these public keys only
    recipients = ["/etc/egosurg/keys/site.recipient", "/etc/egosurg/keys/escrow.recipient"]
    # plaintext = true                 # unencrypted sessions instead: a bench only, warns
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.config_fields import internal, option, validate
from protocol.errors import ConfigError
from protocol.formats.node_config import NAME_HINT, endpoint_like, is_name
from protocol.formats.sealing_config import RigSealingConfig
from protocol.formats.security_config import NO_KEYS, RigSecurityConfig, key_path
from protocol.toml_config import load_toml, read_table
from protocol.wire import MAX_FRAME_BYTES
from protocol.wire.frame_limits import LARGEST_IMAGE_BYTES, frame_message_max_bytes

__all__ = [
    "MIN_RECEIVE_MESSAGES",
    "AgentEndpoint",
    "RigConfig",
    "connect_address",
]

MIN_RECEIVE_MESSAGES = 8  # the smallest receive queue per agent that receive_buffer_mb may give


def _serials(cameras: tuple[int, ...]) -> bool:
    return all(s > 0 for s in cameras)


@dataclass(frozen=True, kw_only=True)
class AgentEndpoint:
    node_id: str = option(test=is_name, must=NAME_HINT)
    frames: str = endpoint_like("tcp://host:5550")
    control: str = endpoint_like("tcp://host:5551")
    # expected serials; a start is refused if one is missing
    cameras: tuple[int, ...] = option((), test=_serials, must="must list camera serial numbers")
    public_key: str = ""  # the agent's public key file: the only key its frames may come from

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class RigConfig:
    rig_name: str = option("rig", test=is_name, must=NAME_HINT)
    fps: float = option(ge=1, le=120)
    control_bind: str = endpoint_like("tcp://127.0.0.1:5560")
    output_dir: str = option(must="the folder sessions are written to")
    agents: tuple[AgentEndpoint, ...] = option(
        test=bool, must="add one [[agents]] table per capture node"
    )
    require_ptp_lock: bool = True
    # 0.2 s: capture-to-durable p99 under 250 ms at the full rig for about 1-2 % of a core more
    # than 0.5 s (BENCHMARKS.md); a crash loses at most this much
    flush_interval_s: float = option(
        0.2, ge=0.01, le=1.0, must="must be 0.01 to 1 s (a crash loses at most this much)"
    )
    max_wait_ms: float = option(500.0, ge=10, le=10_000)
    disk_reserve_gb: float = option(2.0, ge=0, must="must be a non-negative size in GB")
    planned_duration_min: float = option(60.0, gt=0)
    agent_timeout_s: float = option(3.0, ge=0.5, le=60)
    # the MB of queued frames the recorder may hold, all agents
    receive_buffer_mb: float = option(1024.0, ge=1, le=1_000_000)
    # frames received but not yet written (a stalling disk); ~3.5 s of the reference rig's
    # 4 x HD1200 JPEG streams (~75 MB/s); at least one largest legal frame message
    write_queue_mb: float = option(256.0, ge=1, le=1_000_000)
    max_image_bytes: int = option(
        LARGEST_IMAGE_BYTES,
        ge=1024,
        le=MAX_FRAME_BYTES,
        must=f"must be bytes per image, 1024 to {MAX_FRAME_BYTES}; larger images are refused",
    )
    # frames stamped further from the recorder's clock: refused
    max_clock_skew_s: float = option(10.0, ge=0.1, le=86_400)
    security: RigSecurityConfig = field(default_factory=RigSecurityConfig)
    sealing: RigSealingConfig = field(default_factory=RigSealingConfig)
    toml_text: str = internal("")
    source_path: str = internal("")

    def __post_init__(self) -> None:
        validate(self)
        names = [a.node_id for a in self.agents]
        if len(set(names)) != len(names):
            raise ConfigError("two [[agents]] share a node_id; each node needs its own")
        serials = self.expected_cameras
        if len(set(serials)) != len(serials):
            raise ConfigError("a camera serial is listed under two agents")
        self.security.require_keys()
        self.security.check_bind(self.control_bind, "control_bind")
        for i, a in enumerate(self.agents):
            if not a.public_key and not self.security.insecure:
                raise ConfigError(
                    f"agents[{i}] ({a.node_id}): 'public_key' is required (the agent's .key "
                    f"file); {NO_KEYS}"
                )
        self.sealing.require_choice()
        _check_buffers(self)

    @property
    def expected_cameras(self) -> tuple[int, ...]:
        return tuple(s for a in self.agents for s in a.cameras)

    @classmethod
    def from_toml(cls, path: Path | str) -> RigConfig:
        data, text = load_toml(path, "rig config")
        return cls.from_table(data, str(path), text)

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str, text: str = "") -> RigConfig:
        """From rig.toml's parsed ``data``; key paths are relative to ``where``'s folder."""
        cfg = read_table(cls, data, where)
        base = Path(where).parent
        agents = tuple(
            dataclasses.replace(a, public_key=key_path(a.public_key, base)) if a.public_key else a
            for a in cfg.agents
        )
        return dataclasses.replace(
            cfg,
            agents=agents,
            security=cfg.security.resolved(where),
            sealing=cfg.sealing.resolved(where),
            toml_text=text,
            source_path=where,
        )


def _check_buffers(cfg: RigConfig) -> None:
    """The receive and write queues must each hold the largest legal frame messages."""
    largest = frame_message_max_bytes(cfg.max_image_bytes)
    per_agent = cfg.receive_buffer_mb * 1e6 / len(cfg.agents)
    need = MIN_RECEIVE_MESSAGES * largest
    if per_agent < need:
        raise ConfigError(
            f"receive_buffer_mb = {cfg.receive_buffer_mb:g} leaves {per_agent / 1e6:.0f} "
            f"MB per agent, under {MIN_RECEIVE_MESSAGES} of the largest legal frame messages "
            f"({need / 1e6:.0f} MB); raise receive_buffer_mb or lower max_image_bytes"
        )
    if cfg.write_queue_mb * 1e6 < largest:
        raise ConfigError(
            f"write_queue_mb = {cfg.write_queue_mb:g} cannot hold one largest legal "
            f"frame message ({largest / 1e6:.0f} MB); raise write_queue_mb or lower max_image_bytes"
        )


def connect_address(bind: str) -> str:
    """The address a client on the same machine connects to for a bind address."""
    return bind.replace("tcp://*:", "tcp://127.0.0.1:").replace(
        "tcp://0.0.0.0:", "tcp://127.0.0.1:"
    )
