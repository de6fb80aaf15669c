"""Bad input to the capture commands gets one clear line, exit code 2, and no traceback."""

from __future__ import annotations

import pytest

from protocol.errors import ConfigError
from protocol.formats.rig_config import RigConfig
from sim.deploy import free_ports
from tests.conftest import run_egosurg


def _fails_clearly(out, *words: str) -> None:
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert "Traceback" not in out.stderr
    for w in words:
        assert w in out.stderr, out.stderr


def test_missing_and_broken_config_files(tmp_path):
    _fails_clearly(run_egosurg("agent", "--config", str(tmp_path / "nope.toml")), "does not exist")
    bad = tmp_path / "rig.toml"
    bad.write_text("fps = [unclosed\n")
    _fails_clearly(run_egosurg("recorder", "--config", str(bad)), "not valid TOML")
    bad.write_text('fps = 30\ncontrol_bind = "tcp://127.0.0.1:1"\noutput_dir = "x"\n')
    _fails_clearly(run_egosurg("recorder", "--config", str(bad)), "[[agents]]")


def test_no_recorder_answering(tmp_path, monkeypatch):
    from capture_agent.operator.keys_cli import generate

    _, operator = generate(tmp_path / "keys", "operator")
    recorder, _ = generate(tmp_path / "keys", "recorder")
    monkeypatch.setenv("EGOSURG_KEY", str(operator))
    monkeypatch.setenv("EGOSURG_RECORDER_KEY", str(recorder))
    port = free_ports(1)[0]
    out = run_egosurg("record", "start", "--case", "c1", "--recorder", f"tcp://127.0.0.1:{port}")
    _fails_clearly(out, "no recorder answered", "egosurg recorder")
    out = run_egosurg("status", "--recorder", f"tcp://127.0.0.1:{port}")
    _fails_clearly(out, "no recorder answered")


def test_bad_metadata_is_refused_before_anything_is_sent():
    out = run_egosurg(
        "record", "start", "--case", "c1", "--meta", "surgeon", "--recorder", "tcp://127.0.0.1:9"
    )
    _fails_clearly(out, "key=value")


def test_session_tools_on_files_that_are_not_sessions(tmp_path):
    _fails_clearly(run_egosurg("session", "info", str(tmp_path / "missing.h5")), "missing.h5")
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    _fails_clearly(run_egosurg("session", "verify", str(text)), "notes.h5")


@pytest.mark.parametrize(
    ("body", "words"),
    [
        (
            'fps = 30\ncontrol_bind = "tcp://*:1"\noutput_dir = "s"\n[[agents]]\nnode_id = "a"\n'
            'frames = "tcp://h:1"\ncontrol = "tcp://h:2"\n[[agents]]\nnode_id = "a"\n'
            'frames = "tcp://h:3"\ncontrol = "tcp://h:4"\n',
            ["node_id"],
        ),
        (
            'fps = 500\ncontrol_bind = "tcp://*:1"\noutput_dir = "s"\n[[agents]]\nnode_id = "a"\n'
            'frames = "tcp://h:1"\ncontrol = "tcp://h:2"\n',
            ["fps", "1 to 120"],
        ),
        (
            'fps = 30\ncontrol_bind = "tcp://*:1"\noutput_dir = "s"\nflush_interval_s = 5\n'
            '[[agents]]\nnode_id = "a"\nframes = "tcp://h:1"\ncontrol = "tcp://h:2"\n',
            ["flush_interval_s", "crash"],
        ),
        (
            'fps = 30\ncontrol_bind = "tcp://*:1"\noutput_dir = "s"\n[[agents]]\nnode_id = "a"\n'
            'frames = "tcp://h:1"\ncontrol = "tcp://h:2"\ncameras = [1, 1]\n[[agents]]\n'
            'node_id = "b"\nframes = "tcp://h:3"\ncontrol = "tcp://h:4"\ncameras = [1]\n',
            ["serial"],
        ),
    ],
)
def test_bad_rig_config_names_the_field(tmp_path, body, words):
    path = tmp_path / "rig.toml"
    path.write_text(body)
    with pytest.raises(ConfigError) as info:
        RigConfig.from_toml(path)
    for w in words:
        assert w in str(info.value)
