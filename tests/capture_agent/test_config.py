"""node.toml and rig.toml as typed configs (protocol/formats/: node_config.py, rig_config.py,
camera_config.py): a typo or a bad value in any table fails when the file loads, in one line naming
the file, the table and the field; a config built in code is checked the same way; a config
written back reads the same."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from protocol.camera import Resolution
from protocol.errors import ConfigError
from protocol.formats.camera_config import (
    FaultSpec,
    SimSourceConfig,
    VideoSourceConfig,
    ZedSourceConfig,
)
from protocol.formats.node_config import NodeConfig, PtpConfig
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.formats.sealing_config import RigSealingConfig
from protocol.formats.security_config import NodeSecurityConfig, RigSecurityConfig
from protocol.toml_config import dumps

NODE = """\
node_id = "orin-a"
frames_bind = "tcp://10.10.0.11:5550"
control_bind = "tcp://10.10.0.11:5551"

[ptp]
source = "pmc"
require_lock = true

[security]
secret_key = "keys/orin-a.key_secret"
allowed_keys = ["keys/recorder.key", "keys/operator.key"]

[[cameras]]
source = "zed"
serial = 41234567

[[cameras]]
source = "sim"
camera_index = 1
faults = [{ kind = "hang", at_s = 10.0, duration_s = 2.0 }]

[[cameras]]
source = "video"
path = "/data/replay/SN41234567_sbs.mp4"
"""


def _node(tmp_path: Path, text: str = NODE) -> NodeConfig:
    path = tmp_path / "node.toml"
    path.write_text(text)
    return NodeConfig.from_toml(path)


def _fails(tmp_path: Path, text: str, *words: str) -> str:
    with pytest.raises(ConfigError) as info:
        _node(tmp_path, text)
    message = str(info.value)
    assert "\n" not in message and str(tmp_path / "node.toml") in message, message
    for w in words:
        assert w in message, (w, message)
    return message


def test_node_toml_reads_into_typed_ptp_and_camera_configs(tmp_path):
    cfg = _node(tmp_path)
    assert cfg.ptp == PtpConfig(source="pmc", require_lock=True)
    zed, sim, video = cfg.cameras
    assert zed == ZedSourceConfig(serial=41234567)
    assert sim == SimSourceConfig(
        camera_index=1, faults=(FaultSpec(kind="hang", at_s=10.0, duration_s=2.0),)
    )
    assert video == VideoSourceConfig(path="/data/replay/SN41234567_sbs.mp4")
    assert cfg.security.secret_key == str(tmp_path / "keys/orin-a.key_secret")


def test_a_typo_in_ptp_fails_at_load(tmp_path):
    text = NODE.replace("require_lock = true", "requre_lock = true")
    _fails(tmp_path, text, "unknown option 'ptp.requre_lock'", "require_lock", "lock_threshold_ns")
    _fails(tmp_path, NODE.replace('"pmc"', '"gps"'), "ptp.source = 'gps'", "'pmc', 'none'")


def test_an_unknown_key_in_a_camera_table_fails_at_load(tmp_path):
    text = NODE.replace("serial = 41234567", "serail = 41234567")
    _fails(tmp_path, text, "unknown option 'cameras[0].serail'", "serial", "buffer_frames")


def test_a_bad_backend_fails_at_load(tmp_path):
    text = NODE.replace('source = "video"', 'source = "gige"')
    _fails(tmp_path, text, "cameras[2].source = 'gige'", "'sim', 'zed', 'video'")
    text = NODE.replace('source = "video"\n', "")
    _fails(tmp_path, text, "'cameras[2].source' is required")


@pytest.mark.parametrize(
    ("old", "new", "words"),
    [
        ("serial = 41234567", "serial = 41234567\nfps = 90", ["cameras[0].fps = 90", "15, 30"]),
        ("camera_index = 1", "camera_index = 9", ["cameras[1].camera_index = 9", "0 to 3"]),
        ("at_s = 10.0", "at_s = -1.0", ["cameras[1].faults[0].at_s = -1.0", ">= 0"]),
        ('"hang"', '"explode"', ["cameras[1].faults[0].kind = 'explode'"]),
        ("camera_index = 1", 'camera_index = 1\nresolution = "4K"', ["resolution = '4K'"]),
        ('source = "pmc"', 'source = "pmc"\ntimeout_s = 60', ["ptp.timeout_s = 60", "30 s"]),
        ('frames_bind = "tcp', 'jpeg_quality = 0\nframes_bind = "tcp', ["jpeg_quality = 0"]),
        ('frames_bind = "tcp://10.10.0.11:5550"', 'frames_bind = "x"', ["frames_bind = 'x'"]),
    ],
)
def test_a_bad_value_names_file_table_field_and_value(tmp_path, old, new, words):
    assert old in NODE
    _fails(tmp_path, NODE.replace(old, new, 1), *words)


def test_a_config_built_in_code_is_checked():
    with pytest.raises(ConfigError, match="lock_threshold_ns = 0"):
        PtpConfig(lock_threshold_ns=0)
    with pytest.raises(ConfigError, match="fps = 90"):
        ZedSourceConfig(fps=90)
    with pytest.raises(ConfigError, match="buffer_frames = 40"):
        ZedSourceConfig(buffer_frames=40)
    with pytest.raises(ConfigError, match=r"drop_probability = 0\.7"):
        SimSourceConfig(drop_probability=0.7)
    insecure = NodeSecurityConfig(insecure=True)
    cams = (SimSourceConfig(),)
    node: dict[str, Any] = {"node_id": "a", "frames_bind": "tcp://h:1", "control_bind": "tcp://h:2"}
    with pytest.raises(ConfigError, match="queue_frames = 1"):
        NodeConfig(**node, queue_frames=1, cameras=cams, security=insecure)
    with pytest.raises(ConfigError, match=r"\[\[cameras\]\]"):
        NodeConfig(**node, cameras=(), security=insecure)
    with pytest.raises(ConfigError, match="egosurg keys generate"):
        NodeConfig(**node, cameras=cams)
    agent = AgentEndpoint(node_id="a", frames="tcp://h:1", control="tcp://h:2")
    rig: dict[str, Any] = {
        "fps": 30,
        "control_bind": "tcp://h:3",
        "output_dir": "s",
        "agents": (agent,),
    }
    with pytest.raises(ConfigError, match="flush_interval_s = 5"):
        RigConfig(**rig, flush_interval_s=5, security=RigSecurityConfig(insecure=True))
    with pytest.raises(ConfigError, match="public_key"):
        RigConfig(**rig, security=RigSecurityConfig(secret_key="r", operator_keys=("o",)))
    with pytest.raises(ConfigError, match="node_id = 'a b'"):
        AgentEndpoint(node_id="a b", frames="tcp://h:1", control="tcp://h:2")


def test_a_config_written_back_reads_the_same(tmp_path):
    cfg = _node(tmp_path)
    again = _node(tmp_path, dumps(cfg))
    assert again == cfg
    rig = RigConfig(
        fps=30,
        control_bind="tcp://127.0.0.1:5560",
        output_dir="s",
        agents=(AgentEndpoint(node_id="a", frames="tcp://h:1", control="tcp://h:2"),),
        security=RigSecurityConfig(insecure=True),
        sealing=RigSealingConfig(plaintext=True),
    )
    path = tmp_path / "rig.toml"
    path.write_text(dumps(rig))
    loaded = RigConfig.from_toml(path)
    assert loaded.agents == rig.agents and loaded.fps == 30.0 and loaded.toml_text
    assert loaded.max_image_bytes == rig.max_image_bytes


def test_a_camera_resolution_reads_in_any_case(tmp_path):
    cfg = _node(
        tmp_path, NODE.replace("camera_index = 1", 'camera_index = 1\nresolution = "hd1080"')
    )
    assert cfg.cameras[1].resolution is Resolution.HD1080
