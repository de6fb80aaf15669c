"""``node.toml``: one capture agent's config, typed (rig.toml is ``rig_config.py``).

Every option's range or rule is stated once, on its field; a config checks itself when it is made
(``protocol/config_fields.py``), from a file (``protocol/toml_config.py``: an unknown key or a bad
value fails at load, in one line naming the file, the table and the field) or in code.

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
    serial = 41234567                  # source's own options (protocol/formats/camera_config.py)

The node id and endpoint rules here are rig.toml's too (its ``[[agents]]`` name nodes).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

from protocol.config_fields import internal, option, validate
from protocol.formats.camera_config import CameraConfig
from protocol.formats.security_config import NodeSecurityConfig
from protocol.toml_config import load_toml, read_table

__all__ = [
    "ENCODINGS",
    "NAME_HINT",
    "EncodingName",
    "NodeConfig",
    "PtpConfig",
    "endpoint_like",
    "is_name",
]

# The names of protocol.wire.Encoding, as node.toml spells them.
EncodingName = Literal["jpeg", "raw_bgr8"]
ENCODINGS: tuple[EncodingName, ...] = get_args(EncodingName)
PtpSource = Literal["pmc", "none"]  # "none": no PTP (simulation)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")
NAME_HINT = "must be a name of letters, digits, - _ . (at most 32)"


def is_name(value: str) -> bool:
    return bool(_NAME.match(value))


def _endpoint(value: str) -> bool:
    return bool(re.match(r"^(tcp://[^:]+:\d{1,5}|ipc://.+|inproc://.+)$", value))


def endpoint_like(example: str) -> Any:
    return option(test=_endpoint, must=f"must be an endpoint like {example}")


@dataclass(frozen=True, kw_only=True)
class PtpConfig:
    """node.toml's ``[ptp]``: how this node's clock lock is read (capture_agent/agent/ptp.py)."""

    source: PtpSource = "pmc"
    pmc_path: str = option("pmc", test=bool, must="must name the pmc program")
    lock_threshold_ns: int = option(
        1000, gt=0, must="must be > 0 ns (1000 suits hardware timestamping)"
    )
    require_lock: bool = True
    poll_interval_s: float = option(1.0, ge=0.05, le=60, must="must be from 0.05 to 60 seconds")
    timeout_s: float = option(2.0, gt=0, le=30, must="must be > 0 and <= 30 s")
    ptp4l_socket: str = option(
        "/var/run/ptp4l", test=bool, must="must name ptp4l's uds_address (its UNIX socket)"
    )
    pmc_client_dir: str = ""  # "": $RUNTIME_DIRECTORY, else the temp folder
    # CLOCK_REALTIME vs the NIC's clock: further apart, phc2sys is not running or not locked
    system_clock_threshold_ns: int = option(20_000, gt=0, must="must be > 0 ns")
    phc_device: str = ""  # "": the PHC of ptp4l's interface (ethtool -T)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class NodeConfig:
    node_id: str = option(test=is_name, must=NAME_HINT)
    frames_bind: str = endpoint_like("tcp://10.10.0.11:5550")
    control_bind: str = endpoint_like("tcp://10.10.0.11:5551")
    encoding: EncodingName = "jpeg"
    jpeg_quality: int = option(90, ge=1, le=100)
    queue_frames: int = option(120, ge=2, le=10_000)
    status_interval_s: float = option(1.0, ge=0.05, le=60)
    watchdog_timeout_s: float = option(2.0, ge=0.1, le=600)
    reopen_interval_s: float = option(1.0, ge=0.05, le=600)
    ptp: PtpConfig = field(default_factory=PtpConfig)
    cameras: tuple[CameraConfig, ...] = option(test=bool, must="add at least one [[cameras]] table")
    security: NodeSecurityConfig = field(default_factory=NodeSecurityConfig)
    source_path: str = internal("")

    def __post_init__(self) -> None:
        validate(self)
        self.security.require_keys()
        self.security.check_bind(self.frames_bind, "frames_bind")
        self.security.check_bind(self.control_bind, "control_bind")

    @classmethod
    def from_toml(cls, path: Path | str) -> NodeConfig:
        data, _ = load_toml(path, "node config")
        return cls.from_table(data, str(path))

    @classmethod
    def from_table(cls, data: dict[str, Any], where: str) -> NodeConfig:
        """From node.toml's parsed ``data``; key paths are relative to ``where``'s folder."""
        cfg = read_table(cls, data, where)
        return dataclasses.replace(cfg, security=cfg.security.resolved(where), source_path=where)
