"""``egosurg agent --check`` on the sim node and on a ZED node through the fake ZED SDK 5.x:
one table, a row per check, exit 0 only when the node can record."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest

from capture_agent.agent import agent, preflight
from protocol.formats.node_config import NodeConfig
from protocol.toml_config import dumps
from tests.capture_agent.test_zed_source import SERIAL, T0_NS, write_replay, zed_table
from tests.helpers import loopback_sim_node


@pytest.fixture(autouse=True)
def as_service_user(monkeypatch):
    """The checks run as the agent's user (these tests may run as root)."""
    monkeypatch.setattr(preflight, "current_user", lambda: preflight.SERVICE_USER)


def rows(config: NodeConfig) -> dict[str, preflight.Check]:
    return {r.name: r for r in preflight.run_checks(config)}


def zed_node(tmp_path: Path, **camera) -> NodeConfig:
    sim = loopback_sim_node("orin-z", fps=30, seed=1)
    table = {
        "node_id": "orin-z",
        "frames_bind": sim.frames_bind,
        "control_bind": sim.control_bind,
        "ptp": {"source": "none", "require_lock": False},
        "cameras": [{"source": "zed", **zed_table(tmp_path, **camera)}],
        "security": {"insecure": True},
    }
    return NodeConfig.from_table(table, "test node.toml")


@pytest.fixture
def argus(monkeypatch, tmp_path):
    """A listening unix socket standing in for nvargus-daemon's."""
    path = tmp_path / "argus_socket"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.bind(str(path))
        monkeypatch.setattr(preflight, "ARGUS_SOCKET", str(path))
        yield path


def test_the_sim_node_can_record(tmp_path, capsys):
    config = loopback_sim_node("orin-s", fps=10, seed=3, cameras=({}, {}))
    path = tmp_path / "node.toml"
    path.write_text(dumps(config))
    assert agent.main(["--check", "--config", str(path)]) == 0
    table = capsys.readouterr().out
    assert table.splitlines()[-1] == "this node can record"
    for name in ("user", "python", "packages", "ptp", "system clock", "disk", "keys", "ports"):
        assert any(line.startswith(name) and " ok " in line for line in table.splitlines()), name
    assert table.count("opens at SVGA (960x600) 10 fps") == 2
    assert "zed sdk" not in table and "argus" not in table  # no ZED camera here


def test_a_zed_node_with_its_camera_and_sdk_5(fake_sl, argus, tmp_path):
    write_replay(tmp_path / "replay", [T0_NS])
    got = rows(zed_node(tmp_path))
    assert all(r.ok for r in got.values()), [r for r in got.values() if not r.ok]
    assert got["zed sdk"].found == f"ZED SDK {fake_sl.SDK_VERSION}; the SDK lists SN{SERIAL}"
    assert got[f"camera SN{SERIAL}"].found == "opens at SVGA (960x600) 30 fps"
    assert got["argus socket"].found.endswith("is a socket")


@pytest.mark.parametrize(
    "case, row, found, fix",
    [
        ("missing sdk", "zed sdk", "needs pyzed", "get_python_api.py"),
        ("old sdk", "zed sdk", "ZED SDK 4.2.5 found", "the SDK for its JetPack"),
        ("camera absent", f"camera SN{SERIAL + 1}", "CAMERA_NOT_DETECTED", "ZED_Explorer"),
        ("wrong mode", f"camera SN{SERIAL}", "opened at 960x600 15 fps", "ZED_Explorer"),
        ("no argus", "argus socket", "No such file", "nvargus-daemon"),
    ],
)
def test_a_zed_node_that_cannot_record_says_why(
    case, row, found, fix, fake_sl, argus, monkeypatch, tmp_path
):
    write_replay(tmp_path / "replay", [T0_NS], **({"fps": 15} if case == "wrong mode" else {}))
    if case == "missing sdk":
        monkeypatch.setitem(sys.modules, "pyzed", None)
        monkeypatch.delitem(sys.modules, "pyzed.sl", raising=False)
    if case == "old sdk":
        monkeypatch.setattr(fake_sl, "SDK_VERSION", "4.2.5")
    if case == "no argus":
        monkeypatch.setattr(preflight, "ARGUS_SOCKET", str(tmp_path / "nothing"))
    config = zed_node(tmp_path, **({"serial": SERIAL + 1} if case == "camera absent" else {}))
    got = rows(config)
    problems = [r.name for r in got.values() if not r.ok]
    assert problems == [row], problems  # one cause, one row (an SDK problem hides the cameras')
    assert found in got[row].found and fix in got[row].fix
    code, table = preflight.check_node(config)
    assert code == 1 and table.endswith("this node cannot record: 1 problem(s)")
    assert f"fix: {got[row].fix}" in table


def test_ports_in_use_and_root_are_problems(monkeypatch):
    config = loopback_sim_node("orin-p", fps=10, seed=3)
    host, port = config.control_bind.removeprefix("tcp://").rsplit(":", 1)
    monkeypatch.setattr(preflight, "current_user", lambda: "root")
    with socket.socket() as holder:
        holder.bind((host, int(port)))
        holder.listen()
        got = rows(config)
    assert not got["ports"].ok and f"{config.control_bind}: in use" in got["ports"].found
    assert "systemctl stop egosurg-agent" in got["ports"].fix
    assert not got["user"].ok and "sudo -u egosurg" in got["user"].fix
