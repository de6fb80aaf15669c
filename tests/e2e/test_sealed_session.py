"""A sealed session end to end: the deployed sim rig (real agent and recorder processes) records
for its site key, and the ``egosurg session`` readers open it with the site identity and refuse
it, in one line naming the recipients, without one or with another."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import pytest

from protocol.formats.wand import WandSpec
from protocol.sealing import generate_identity, write_identity
from sim.deploy import SimRigSpec
from sim.truth import true_rig_calibration
from sim.world import World
from tests.helpers import record_sim_session, run_egosurg

pytestmark = pytest.mark.slow

JPEG_START = b"\xff\xd8\xff"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """(the sim rig's files, the session it recorded): 2 cameras, about 3 s."""
    directory = tmp_path_factory.mktemp("sealed")
    spec = SimRigSpec(seed=4, cameras=2, fps=15.0, prerender_s=1.0, drop_probability=0.0)
    return directory, record_sim_session(directory, spec, "sealed-case", 3.0)


def _env(identity: Path | None) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("EGOSURG_IDENTITY", None)
    if identity is not None:
        env["EGOSURG_IDENTITY"] = str(identity)
    return env


def _refused(done, *words: str) -> str:
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_the_recorded_session_holds_ciphertext_where_images_were(recorded):
    _, session = recorded
    with h5py.File(session, "r") as f:
        for serial in f["cameras"]:
            blob = bytes(f["cameras"][serial]["left_bytes"][:65536])
            assert blob and JPEG_START not in blob


def test_session_readers_work_with_the_site_identity(recorded, tmp_path):
    directory, session = recorded
    identity = directory / "reader-keys" / "sim-site.identity"
    env = _env(identity)
    done = run_egosurg("session", "info", str(session), env=env)
    assert done.returncode == 0, done.stderr
    assert "session sealed-case" in done.stdout
    done = run_egosurg("session", "verify", str(session), "--identity", str(identity))
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip().endswith("OK")
    out = tmp_path / "frames"
    done = run_egosurg("session", "export-frames", str(session), "--out", str(out), env=env)
    assert done.returncode == 0, done.stderr
    pngs = list(out.rglob("*.png"))
    assert pngs and all(p.read_bytes().startswith(b"\x89PNG") for p in pngs)


def test_session_readers_refuse_without_an_identity_in_one_line(recorded, tmp_path):
    """export-frames needs the images: refused in one line naming the recipients."""
    _, session = recorded
    args = ("export-frames", str(session), "--out", str(tmp_path / "none"))
    line = _refused(run_egosurg("session", *args, env=_env(None)), "sim-site (key id")
    assert "--identity FILE" in line and "EGOSURG_IDENTITY" in line
    assert not (tmp_path / "none").exists() or not list((tmp_path / "none").rglob("*.png"))


def test_info_and_verify_read_the_structure_without_an_identity(recorded):
    """What stays readable without a key (docs/session.md, "Sealed sessions"): info shows the
    session and says what it is sealed for; verify checks every image's checksum."""
    _, session = recorded
    env = _env(None)
    info = run_egosurg("session", "info", str(session), env=env)
    assert info.returncode == 0 and "Traceback" not in info.stderr, info.stderr
    assert "session sealed-case" in info.stdout
    assert "sealed for sim-site (key id" in info.stdout and "--identity FILE" in info.stdout
    verify = run_egosurg("session", "verify", str(session), env=env)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    assert "note: sealed for" in verify.stdout and ": OK (1 note(s))" in verify.stdout


def test_session_readers_refuse_another_sites_identity_in_one_line(recorded, tmp_path):
    _, session = recorded
    _, other = write_identity(generate_identity("other-site"), tmp_path / "keys")
    done = run_egosurg("session", "info", str(session), "--identity", str(other))
    _refused(done, "sim-site")


def test_a_damaged_identity_file_is_one_line(recorded, tmp_path):
    _, session = recorded
    exposed = tmp_path / "exposed.identity"
    exposed.write_text("egosurg-identity v1\n")
    exposed.chmod(0o644)
    done = run_egosurg("session", "info", str(session), "--identity", str(exposed))
    _refused(done, "exposed.identity")


def test_calibrate_and_reconstruct_refuse_a_sealed_session_without_an_identity(recorded, tmp_path):
    """The same one line from the other readers, before any work; with the identity,
    calibrate gets past the session to the wand (this session holds none)."""
    directory, session = recorded
    wand, calibration = tmp_path / "wand.toml", tmp_path / "calibration.toml"
    wand.write_text(WandSpec().to_toml())
    true_rig_calibration(World.from_seed(4)).write(calibration)
    calibrate = ("calibrate", str(session), "--wand", str(wand), "--out", "c.toml")
    reconstruct = ("reconstruct", str(session), "--calibration", str(calibration))
    commands = (
        (*calibrate, "--max-sets", "10"),
        (*reconstruct, "--at", "1", "--out", "one"),
        (*reconstruct, "--every", "1s", "--out", "case"),
    )
    for args in commands:
        _refused(run_egosurg(*args, cwd=tmp_path, env=_env(None)), "sim-site (key id")
    identity = directory / "reader-keys" / "sim-site.identity"
    done = run_egosurg(*commands[0], "--identity", str(identity), cwd=tmp_path, env=_env(None))
    assert "sim-site" not in done.stderr and "Traceback" not in done.stderr, done.stderr
