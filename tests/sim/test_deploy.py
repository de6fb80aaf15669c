"""sim/deploy.py writes the simulated rig's node.toml and rig.toml with the house's TOML writer;
the files read back, through capture_agent's typed configs, with the spec's values."""

from __future__ import annotations

from typing import Any

from capture_agent.camera_config import FaultSpec, SimSourceConfig
from capture_agent.config import NodeConfig, PtpConfig, RigConfig
from sim.deploy import SimRigSpec, write_sim_rig


def test_the_written_configs_read_back_with_the_spec_values(tmp_path):
    hang: dict[str, Any] = {"kind": "hang", "at_s": 1.0, "duration_s": 2.0}
    spec = SimRigSpec(seed=0, cameras=3, fps=15.0, jpeg_quality=80, faults={2: [hang]})
    files = write_sim_rig(tmp_path, spec)
    rig = RigConfig.from_toml(files.rig_config)
    assert rig.fps == 15.0 and rig.disk_reserve_gb == 0.5 and not rig.require_ptp_lock
    assert {a.node_id: a.cameras for a in rig.agents} == files.serials_by_node
    assert rig.security.public_key == str(tmp_path / "keys" / "recorder.key")
    assert all(a.public_key == str(tmp_path / "keys" / f"{a.node_id}.key") for a in rig.agents)
    cameras: list[SimSourceConfig] = []
    for node, path in files.node_configs.items():
        cfg = NodeConfig.from_toml(path)
        assert cfg.node_id == node and cfg.jpeg_quality == 80
        assert cfg.ptp == PtpConfig(source="none", require_lock=False)
        assert cfg.security.secret_key == str(tmp_path / "keys" / f"{node}.key_secret")
        cameras += [c for c in cfg.cameras if isinstance(c, SimSourceConfig)]
    assert len(cameras) == 3
    by_index = {c.camera_index: c for c in cameras}
    assert {c.epoch_unix_ns for c in cameras} == {files.epoch_unix_ns}
    assert by_index[2].faults == (FaultSpec(**hang),)
    assert by_index[0].pre_encode == "jpeg" and by_index[0].jpeg_quality == 80
    assert files.node_configs["orin-a"].read_text().startswith("# the simulated node orin-a")


def test_an_insecure_rig_says_so_in_every_file(tmp_path):
    files = write_sim_rig(tmp_path, SimRigSpec(seed=0, cameras=1, insecure=True, pre_encode=False))
    assert RigConfig.from_toml(files.rig_config).security.insecure
    (path,) = files.node_configs.values()
    cfg = NodeConfig.from_toml(path)
    assert cfg.security.insecure and cfg.cameras[0].pre_encode is None  # type: ignore[union-attr]
    assert not (tmp_path / "keys").exists()
