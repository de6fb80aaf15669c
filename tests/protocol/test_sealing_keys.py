"""Site keys as a security officer relies on them: ``egosurg keys generate --kind site`` writes an
owner-only identity in an owner-only folder and never overwrites one; readers take the identity
from ``--identity`` or ``$EGOSURG_IDENTITY`` and refuse a missing, exposed or malformed one in
one line that names the problem, never a traceback."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from protocol import cli
from protocol.sealing import (
    IDENTITY_ENV,
    IdentityError,
    KeyBlock,
    PayloadContext,
    Sealer,
    load_identity,
    load_recipient,
    new_data_key,
    new_session_uid,
    unwrap_data_key,
    wrap_data_key,
)

IMAGE = PayloadContext(field="image", camera_serial=7, row=1, side="right", capture_unix_ns=5)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _keys(capsys, *args: str) -> tuple[int, str, str]:
    code = cli.main(["keys", *args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def site(tmp_path, capsys) -> Path:
    """The identity file of a freshly generated site key."""
    code, _, err = _keys(
        capsys, "generate", "--kind", "site", "--out", str(tmp_path / "k"), "--name", "hospital-a"
    )
    assert code == 0, err
    return tmp_path / "k" / "hospital-a.identity"


def test_generate_writes_an_owner_only_identity_and_a_readable_recipient(site):
    recipient = site.with_suffix(".recipient")
    assert _mode(site.parent) == 0o700 and _mode(site) == 0o600 and _mode(recipient) == 0o644
    assert site.read_text().count("egosurg-identity v1") == 1
    assert "secret" not in recipient.read_text().replace("SECRET", "")
    assert load_recipient(recipient) == load_identity(site).recipient


def test_generate_never_overwrites_a_key(site, capsys):
    before = site.read_bytes()
    code, _, err = _keys(
        capsys, "generate", "--kind", "site", "--out", str(site.parent), "--name", "hospital-a"
    )
    assert code == 2 and "never overwritten" in err and err.count("\n") == 1
    assert site.read_bytes() == before


def test_a_link_key_is_still_the_default_kind(tmp_path, capsys):
    code, _, _ = _keys(capsys, "generate", "--out", str(tmp_path), "--name", "recorder")
    assert code == 0 and (tmp_path / "recorder.key_secret").exists()


def test_the_identity_comes_from_the_option_else_the_environment(
    site, tmp_path, monkeypatch, capsys
):
    monkeypatch.delenv(IDENTITY_ENV, raising=False)
    code, _, err = _keys(capsys, "identity")
    assert code == 2 and "--identity FILE" in err and IDENTITY_ENV in err
    monkeypatch.setenv(IDENTITY_ENV, str(site))
    code, out, _ = _keys(capsys, "identity")
    assert code == 0 and "hospital-a (key id" in out
    monkeypatch.setenv(IDENTITY_ENV, str(tmp_path / "gone.identity"))
    code, out, _ = _keys(capsys, "identity", "--identity", str(site))
    assert code == 0 and "hospital-a" in out  # the option wins over the environment


def _with_line(text: str, field: str, value: str | None) -> str:
    lines = [ln for ln in text.splitlines() if not ln.startswith(f"{field}:")]
    return "\n".join(lines + ([f"{field}: {value}"] if value is not None else [])) + "\n"


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda t: t.replace("egosurg-identity v1", "egosurg-identity v9"), "not 'egosurg-id"),
        (lambda t: "", "starts with 'nothing'"),
        (lambda t: _with_line(t, "secret", None), "fields"),
        (lambda t: t + "name: again\n", "repeated field"),
        (lambda t: t + "just words\n", "not 'field: value'"),
        (lambda t: _with_line(t, "secret", "not*base64"), "secret key is not 32 bytes"),
        (lambda t: _with_line(t, "public", "AAAA"), "public key is not 32 bytes"),
        (lambda t: _with_line(t, "key-id", "00" * 8), "key-id"),
        (lambda t: _with_line(t, "kind", "link"), "kind 'link'"),
        (lambda t: _with_line(t, "name", "../x"), "key name"),
        (lambda t: _with_line(t, "secret", "A" * 43 + "="), "does not belong to its secret"),
        (lambda t: t.encode("utf-16").decode("latin-1"), "identity"),
    ],
    ids=[
        "version",
        "empty",
        "no-secret",
        "repeated",
        "junk",
        "base64",
        "short",
        "key-id",
        "kind",
        "name",
        "mismatch",
        "utf16",
    ],
)
def test_a_malformed_identity_is_one_line_naming_the_problem(site, capsys, change, words):
    site.write_text(change(site.read_text()))
    site.chmod(0o600)
    code, _, err = _keys(capsys, "identity", "--identity", str(site))
    assert code == 2 and err.count("\n") == 1 and words in err and str(site) in err, err


def test_an_identity_others_can_read_is_refused(site, capsys):
    site.chmod(0o640)
    code, _, err = _keys(capsys, "identity", "--identity", str(site))
    assert code == 2 and "mode 0640" in err and f"chmod 600 {site}" in err


@pytest.mark.parametrize("what", ["missing", "folder", "recipient"])
def test_a_missing_or_wrong_identity_file_is_one_line(site, capsys, what):
    path = {
        "missing": site.with_name("x.identity"),
        "folder": site.parent,
        "recipient": site.with_suffix(".recipient"),
    }[what]
    code, _, err = _keys(capsys, "identity", "--identity", str(path))
    assert code == 2 and err.count("\n") == 1 and str(path) in err, err


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_an_unreadable_identity_is_one_line(site, capsys):
    site.chmod(0o000)
    code, _, err = _keys(capsys, "identity", "--identity", str(site))
    assert code == 2 and "cannot be read by this user" in err


def test_the_installed_command_prints_no_traceback(site, tmp_path):
    """The real command, as a user runs it, on an identity that group may read."""
    site.chmod(0o644)
    done = subprocess.run(
        [sys.executable, "-m", "protocol.cli", "keys", "identity", "--identity", str(site)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().count("\n") == 0 and "mode 0644" in done.stderr


def test_public_recipient_files_seal_and_only_the_identity_opens(site):
    """What a recorder holds (the .recipient file) seals a session; it cannot open it."""
    recipient = load_recipient(site.with_suffix(".recipient"))
    uid, data_key = new_session_uid(), new_data_key()
    block = wrap_data_key(data_key, [recipient], uid).to_bytes()
    sealed = Sealer(data_key, uid).seal(b"a frame", IMAGE)
    with pytest.raises(IdentityError, match="not 'egosurg-identity v1'"):
        load_identity(site.with_suffix(".recipient"))
    parsed = KeyBlock.from_bytes(block)
    reader = Sealer(unwrap_data_key(parsed, [load_identity(site)]), parsed.session_uid)
    assert reader.open(sealed, IMAGE) == b"a frame"


def test_keys_show_names_the_recipient_and_never_prints_the_secret(site, capsys):
    secret_line = next(ln for ln in site.read_text().splitlines() if ln.startswith("secret:"))
    key_id = load_identity(site).recipient.key_id.hex()
    for path in (site, site.with_suffix(".recipient")):
        code, out, _ = _keys(capsys, "show", str(path))
        assert code == 0 and f"hospital-a (key id {key_id})" in out
        assert secret_line.split(":", 1)[1].strip() not in out
