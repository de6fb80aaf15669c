"""rig.toml's ``[sealing]``: a recorder seals for the recipients it names, holds only their public
keys, and says in one line what to do when the table is missing or a key file is wrong.

Real key files (``egosurg keys generate --kind site``), real rig.toml files and the real
``egosurg recorder`` process for the errors a user sees.
"""

from __future__ import annotations

import base64
import logging
import stat
from pathlib import Path

import pytest
import zmq.auth
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey

from capture_agent.operator.control import format_status
from capture_agent.recorder.recorder import Recorder
from capture_agent.recorder.sealing import load_recipients
from protocol.errors import ConfigError
from protocol.formats.rig_config import RigConfig
from protocol.sealing import IdentityError, load_identity
from sim.deploy import SimRigSpec, free_ports, write_sim_rig
from tests.helpers import run_egosurg

RIG = """\
rig_name = "seal"
fps = 15
control_bind = "tcp://127.0.0.1:{port}"
output_dir = "sessions"
require_ptp_lock = false

[security]
insecure = true

[[agents]]
node_id = "orin-a"
frames = "tcp://127.0.0.1:1"
control = "tcp://127.0.0.1:2"
"""


def _rig(folder: Path, sealing: str) -> Path:
    path = folder / "rig.toml"
    path.write_text(RIG.format(port=free_ports(1)[0]) + sealing)
    return path


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """A site key pair and an escrow one, made by the real command."""
    folder = tmp_path_factory.mktemp("reader") / "keys"
    for name in ("site", "escrow"):
        done = run_egosurg(
            "keys", "generate", "--kind", "site", "--name", name, "--out", str(folder)
        )
        assert done.returncode == 0, done.stderr
    return folder


def test_a_rig_toml_that_says_nothing_about_sealing_is_refused_with_what_to_do(tmp_path):
    with pytest.raises(ConfigError) as info:
        RigConfig.from_toml(_rig(tmp_path, ""))
    text = str(info.value)
    assert "\n" not in text
    for words in ("[sealing]", "egosurg keys generate --kind site", ".recipient", "plaintext"):
        assert words in text


@pytest.mark.parametrize(
    ("table", "words"),
    [
        ('recipients = ["k/site.recipient"]\nplaintext = true\n', "contradict"),
        ('recipients = ["k/site.identity"]\n', "secret key"),
        ('recipients = ["a.recipient", "a.recipient"]\n', "listed twice"),
        ("recipients = []\n", "plaintext = true"),
        ('plaintext = "yes"\n', "plaintext"),
        ('recipient = ["k/site.recipient"]\n', "unknown option 'sealing.recipient'"),
    ],
)
def test_a_wrong_sealing_table_is_one_line_naming_the_problem(tmp_path, table, words):
    with pytest.raises(ConfigError) as info:
        RigConfig.from_toml(_rig(tmp_path, "[sealing]\n" + table))
    assert words in str(info.value) and "\n" not in str(info.value)


def test_recipient_paths_are_relative_to_rig_toml(tmp_path, site):
    cfg = RigConfig.from_toml(_rig(tmp_path, '[sealing]\nrecipients = ["keys/site.recipient"]\n'))
    assert cfg.sealing.recipients == (str(tmp_path / "keys" / "site.recipient"),)
    absolute = str(site / "site.recipient")
    cfg = RigConfig.from_toml(_rig(tmp_path, f'[sealing]\nrecipients = ["{absolute}"]\n'))
    assert load_recipients(cfg.sealing, "test")[0].name == "site"


def test_the_recorder_loads_every_recipient_at_start(tmp_path, site, caplog):
    sealing = f'[sealing]\nrecipients = ["{site}/site.recipient", "{site}/escrow.recipient"]\n'
    caplog.set_level(logging.INFO)
    recorder = Recorder(RigConfig.from_toml(_rig(tmp_path, sealing)))
    assert [r.name for r in recorder.recipients] == ["site", "escrow"]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("sealed for site (key id" in r.getMessage() for r in caplog.records)


def _recorder_error(folder: Path, sealing: str) -> str:
    """What ``egosurg recorder`` says (exit 2, one line, no traceback) about ``sealing``."""
    done = run_egosurg("recorder", "--config", str(_rig(folder, sealing)), timeout=60)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    return lines[0]


def test_a_missing_or_damaged_recipient_file_stops_the_recorder_in_one_line(tmp_path, site):
    line = _recorder_error(tmp_path, '[sealing]\nrecipients = ["keys/gone.recipient"]\n')
    assert "gone.recipient does not exist" in line and "[sealing]" in line
    damaged = tmp_path / "damaged.recipient"
    damaged.write_text((site / "site.recipient").read_text().replace("key-id: ", "key-id: 0"))
    line = _recorder_error(tmp_path, '[sealing]\nrecipients = ["damaged.recipient"]\n')
    assert "damaged.recipient" in line and "key-id" in line
    curve = tmp_path / "recorder.recipient"  # a CURVE key file, not a sealing key
    zmq.auth.create_certificates(tmp_path, "curve")
    curve.write_text((tmp_path / "curve.key").read_text())
    line = _recorder_error(tmp_path, '[sealing]\nrecipients = ["recorder.recipient"]\n')
    assert "is it the right file?" in line


def test_a_recorder_refuses_a_secret_identity_named_as_a_recipient(tmp_path, site):
    # the public half of an identity would do, but the secret must not live on a recorder
    hidden = tmp_path / "site-copy.recipient"
    hidden.write_text((site / "site.identity").read_text())
    line = _recorder_error(tmp_path, '[sealing]\nrecipients = ["site-copy.recipient"]\n')
    assert "secret identity" in line and "site.recipient" in line
    twice = f'"{site}/site.recipient", "{site}/site.recipient.copy"'
    (site / "site.recipient.copy").write_text((site / "site.recipient").read_text())
    line = _recorder_error(tmp_path, f"[sealing]\nrecipients = [{twice}]\n")
    assert "same key as site" in line


def test_plaintext_sessions_warn_at_every_start(tmp_path, caplog):
    for _ in range(2):
        caplog.clear()
        Recorder(RigConfig.from_toml(_rig(tmp_path, "[sealing]\nplaintext = true\n")))
        warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert any("PLAINTEXT sessions" in w for w in warned)


def test_status_says_how_sessions_are_stored(tmp_path, site):
    """`egosurg status` tells the operator whether the rig writes patient video in clear."""
    plain = Recorder(RigConfig.from_toml(_rig(tmp_path, "[sealing]\nplaintext = true\n")))
    st = plain.status()
    assert st["sessions"] == {"sealed": False, "recipients": []}
    assert "sessions: PLAINTEXT" in format_status(st)
    names = f'"{site}/site.recipient", "{site}/escrow.recipient"'
    sealed = Recorder(RigConfig.from_toml(_rig(tmp_path, f"[sealing]\nrecipients = [{names}]\n")))
    printed = format_status(sealed.status())
    assert "sessions: sealed for site.recipient, escrow.recipient" in printed


def _x25519_public(secret: bytes) -> bytes:
    return X25519PrivateKey.from_private_bytes(secret).public_key().public_bytes_raw()


def test_the_recorder_host_holds_no_key_that_opens_its_sessions(tmp_path):
    """The deployed sim rig: its rig.toml and the recorder's key folder hold public recipient
    keys only; no file there is an identity, and no secret there (the CURVE keys are X25519
    keys too) belongs to a recipient."""
    files = write_sim_rig(tmp_path, SimRigSpec(seed=0, cameras=1))
    cfg = RigConfig.from_toml(files.rig_config)
    recipients = load_recipients(cfg.sealing, "test")
    assert recipients and files.identity is not None
    keys = {Path(p).parent for p in cfg.sealing.recipients} | {Path(cfg.security.secret_key).parent}
    assert keys == {files.keys_dir}
    assert files.identity.parent != files.keys_dir
    # the identity is where a reader keeps it: owner-only, and it opens what the rig seals for
    assert load_identity(files.identity).recipient == recipients[0]
    assert stat.S_IMODE(files.identity.stat().st_mode) == 0o600
    publics = {r.public for r in recipients}
    for path in [files.rig_config, *sorted(files.keys_dir.iterdir())]:
        text = path.read_text()
        assert "egosurg-identity" not in text and "secret:" not in text, path
        with pytest.raises(IdentityError):
            load_identity(path)
        if path.suffix == ".key_secret":  # a CURVE secret: never a recipient's
            secret = zmq.auth.load_certificate(path)[1]
            assert secret is not None
            assert _x25519_public(zmq.utils.z85.decode(secret)) not in publics, path
    # and a base64 blob in rig.toml is not a hidden secret either
    for word in files.rig_config.read_text().split('"'):
        try:
            raw = base64.b64decode(word, validate=True)
        except ValueError:
            continue
        assert len(raw) != 32 or _x25519_public(raw) not in publics


def test_a_sim_rig_for_measuring_plaintext_is_explicit(tmp_path):
    files = write_sim_rig(tmp_path, SimRigSpec(seed=0, cameras=1, plaintext=True))
    assert RigConfig.from_toml(files.rig_config).sealing.plaintext
    assert files.identity is None
    assert "EGOSURG_IDENTITY" not in files.reader_env()
