"""``egosurg sim roles`` and ``egosurg sim contact`` on a sealed session, as a user runs them:
the seed, phase and contact script are sealed case metadata, opened with ``--identity``; the
files they write are the same as from the same session stored plaintext; without an identity
(and without ``--seed``) the command says in one line what to pass."""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.sealing import generate_identity, write_identity
from protocol.session import CameraInfo, SessionWriter
from sim.timing import SIM_EPOCH_UNIX_NS
from tests.helpers import run_egosurg

SERIAL = 101
META = {"source": "egosurg sim eval-set", "phase": "intraoperative", "seed": "3", "contact": "1"}
SET_TIMES_S = (2.0, 2.1, 2.2, 2.3)


def _session(path: Path, recipients) -> Path:
    """A sim session's metadata and sets (tiny raw images: the commands read no image)."""
    camera = CameraInfo(
        camera_serial=SERIAL,
        node_id="orin-a",
        resolution="TINY",
        width=2,
        height=2,
        fps_nominal=10.0,
        encoding="raw_bgr8",
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with SessionWriter(
        path,
        session_name="sim-intraoperative-seed3-contact",
        case_metadata=META,
        cameras=[camera],
        tolerance_ns=50_000_000,
        software_version="test",
        started_unix_ns=SIM_EPOCH_UNIX_NS,
        recipients=recipients,
    ) as w:
        for k, t_s in enumerate(SET_TIMES_S):
            stamp = SIM_EPOCH_UNIX_NS + round(t_s * 1e9)
            row = w.append_frame(
                SERIAL,
                left=bytes(12),
                right=bytes(12),
                capture_unix_ns=stamp,
                host_receive_unix_ns=stamp,
                recorder_receive_unix_ns=stamp,
                frame_index=k,
                seq=k,
                ptp_offset_ns=0,
                ptp_locked=True,
            )
            w.append_set(stamp, [row], 0)
    return path


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("sealed-sim")
    public, identity = write_identity(generate_identity("site-a"), root / "reader-keys")
    from protocol.sealing import load_recipient

    return {
        "sealed": _session(root / "sealed" / "session.h5", [load_recipient(public)]),
        "plain": _session(root / "plain" / "session.h5", []),
        "identity": identity,
        "root": root,
    }


def _env_without_identity() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k != "EGOSURG_IDENTITY"}


def test_roles_of_a_sealed_session_open_its_seed_with_the_identity(sessions, tmp_path):
    env = _env_without_identity()
    sealed, plain = tmp_path / "sealed.toml", tmp_path / "plain.toml"
    done = run_egosurg(
        "sim", "roles", str(sessions["sealed"]), "--identity", str(sessions["identity"]),
        "--every", "0.1", "--out", str(sealed), env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = run_egosurg(
        "sim", "roles", str(sessions["plain"]), "--every", "0.1", "--out", str(plain), env=env
    )
    assert done.returncode == 0, done.stderr
    assert sealed.read_text() == plain.read_text()  # same seed, phase, contact and session


def test_roles_of_a_sealed_session_without_identity_or_seed_say_what_to_pass(sessions, tmp_path):
    done = run_egosurg(
        "sim", "roles", str(sessions["sealed"]), "--out", str(tmp_path / "r.toml"),
        env=_env_without_identity(),
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "is sealed" in lines[0] and "--identity" in lines[0] and "--seed" in lines[0]
    assert "site-a" in lines[0]  # the recipient whose identity opens it
    assert not (tmp_path / "r.toml").exists()


def test_contact_of_a_sealed_session_opens_with_the_identity_and_refuses_without(
    sessions, tmp_path
):
    env = _env_without_identity()
    outs = {}
    for name, extra in (("sealed", ["--identity", str(sessions["identity"])]), ("plain", [])):
        field, truth = tmp_path / f"{name}.toml", tmp_path / f"{name}.csv"
        done = run_egosurg(
            "sim", "contact", str(sessions[name]), *extra, "--field-out", str(field),
            "--truth-out", str(truth), env=env,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        outs[name] = (field.read_text(), truth.read_text())
    assert outs["sealed"] == outs["plain"]
    done = run_egosurg(
        "sim", "contact", str(sessions["sealed"]), "--field-out", str(tmp_path / "f.toml"),
        "--truth-out", str(tmp_path / "t.csv"), env=env,
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "is sealed" in lines[0] and "--identity" in lines[0], done.stderr
    assert not (tmp_path / "f.toml").exists()
