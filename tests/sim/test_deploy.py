"""sim/deploy.py builds the simulated rig's node and rig configs (protocol/formats/) and writes
them with the house's TOML writer; the files read back with the spec's values, and the simulator
is the rig its camera tables name."""

from __future__ import annotations

import os

import psutil
import pytest

from protocol.errors import ConfigError
from protocol.formats.camera_config import SIM_PHASES, SIM_RIG_CAMERAS, FaultSpec, SimSourceConfig
from protocol.formats.node_config import NodeConfig, PtpConfig
from protocol.formats.rig_config import RigConfig
from sim.deploy import SimRig, SimRigSpec, render_threads_per_agent, write_sim_rig
from sim.phases import PHASES
from sim.rig import MOUNTS_M
from sim.world import World


def test_the_written_configs_read_back_with_the_spec_values(tmp_path):
    hang = FaultSpec(kind="hang", at_s=1.0, duration_s=2.0)
    spec = SimRigSpec(seed=0, cameras=3, fps=15.0, jpeg_quality=80, faults={2: (hang,)})
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
    assert by_index[2].faults == (hang,)
    assert by_index[0].pre_encode == "jpeg" and by_index[0].jpeg_quality == 80
    assert files.node_configs["orin-a"].read_text().startswith("# the simulated node orin-a")


def test_an_insecure_rig_says_so_in_every_file(tmp_path):
    files = write_sim_rig(tmp_path, SimRigSpec(seed=0, cameras=1, insecure=True, pre_encode=False))
    assert RigConfig.from_toml(files.rig_config).security.insecure
    (path,) = files.node_configs.values()
    cfg = NodeConfig.from_toml(path)
    assert cfg.security.insecure and cfg.cameras[0].pre_encode is None  # type: ignore[union-attr]
    # no link keys; the sessions are still sealed (plaintext is a setting of its own)
    assert sorted(p.name for p in (tmp_path / "keys").iterdir()) == ["sim-site.recipient"]
    assert not RigConfig.from_toml(files.rig_config).sealing.plaintext


def test_the_simulator_is_the_rig_a_sim_camera_table_names():
    """protocol/ states a sim camera's phases and camera count (it may not import sim/)."""
    assert PHASES == SIM_PHASES
    assert len(MOUNTS_M) == SIM_RIG_CAMERAS == len(World.from_seed(0).rig)


def test_a_bad_value_in_the_spec_fails_when_the_rig_is_written(tmp_path):
    with pytest.raises(ConfigError, match="jpeg_quality = 0"):
        write_sim_rig(tmp_path, SimRigSpec(seed=0, cameras=1, jpeg_quality=0))


def test_the_agents_share_the_cores_among_their_renderers():
    """Agents on one machine run no more renderer threads together than it has cores (each at
    least one), and one agent alone renders on every core."""
    cores = len(os.sched_getaffinity(0))
    assert render_threads_per_agent(1) == cores
    for agents in range(2, 9):
        threads = render_threads_per_agent(agents)
        assert threads >= 1 and (agents * threads <= cores or threads == 1)


def test_each_agent_process_gets_its_share_and_a_users_setting_wins(tmp_path, monkeypatch):
    """The real agent processes' environment: NUMBA_NUM_THREADS is the rig's share, or the
    user's own value when one is set (the recorder renders nothing and gets none)."""
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    files = write_sim_rig(tmp_path / "rig", SimRigSpec(seed=0, resolution="SVGA"))
    assert len(files.node_configs) == 2

    def threads_seen(**kwargs: int) -> dict[str, str | None]:
        rig = SimRig(files, **kwargs).start()
        try:
            return {
                name: psutil.Process(proc.pid).environ().get("NUMBA_NUM_THREADS")
                for name, proc in rig.procs.items()
            }
        finally:
            rig.close()

    share = str(render_threads_per_agent(2))
    assert threads_seen() == {"agent-orin-a": share, "agent-orin-b": share, "recorder": None}
    assert set(threads_seen(render_threads=0).values()) == {None}  # Numba's own default
    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")
    assert set(threads_seen().values()) == {"3"}
    with pytest.raises(ValueError, match="render_threads=-1"):
        SimRig(files, render_threads=-1)
