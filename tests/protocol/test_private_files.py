"""The ``egosurg`` entry's owner-only umask: what a command makes is 0600 / 0700 whatever the
shell's umask, a caller in the same process gets its own umask back, and the files meant to be
copied (a link's public key, a site's ``.recipient``) keep their explicit 0644."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from protocol import cli
from tests.helpers import run_egosurg


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_command_run_in_this_process_writes_owner_only_and_gives_the_umask_back(tmp_path):
    old = os.umask(0o022)
    try:
        out = tmp_path / "made" / "wand.toml"
        assert cli.main(["sim", "wand-file", "--out", str(out)]) == 0
        assert os.umask(0o022) == 0o022  # the caller's umask is back
    finally:
        os.umask(old)
    assert _mode(out) == 0o600 and _mode(out.parent) == 0o700


def test_public_key_files_stay_readable_and_secrets_stay_owner_only(tmp_path):
    old = os.umask(0o022)
    try:
        link = run_egosurg("keys", "generate", "--out", str(tmp_path / "link"), "--name", "node")
        site = run_egosurg(
            "keys", "generate", "--kind", "site", "--name", "site", "--out", str(tmp_path / "s")
        )
    finally:
        os.umask(old)
    assert link.returncode == 0 and site.returncode == 0, link.stderr + site.stderr
    assert _mode(tmp_path / "link" / "node.key") == 0o644
    assert _mode(tmp_path / "link" / "node.key_secret") == 0o600
    assert _mode(tmp_path / "s" / "site.recipient") == 0o644
    assert _mode(tmp_path / "s" / "site.identity") == 0o600
    assert _mode(tmp_path / "link") == 0o700 and _mode(tmp_path / "s") == 0o700
