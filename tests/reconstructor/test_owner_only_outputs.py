"""Nothing the ``egosurg`` command writes is readable by group or others, whatever the shell's
umask: a chain of real commands over a tiny session (reconstruct a case and one timestamp with a
depth cache, case export, sim roles, replay with the real frames inset, render, session
export-frames) run as subprocesses under the common umask 022; every file and folder they made
or rewrote is checked. The commands that write plaintext patient imagery say so on stderr."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from protocol.formats.rig_calibration import RigCalibration
from tests.helpers import run_egosurg
from tests.reconstructor.tiny import tiny_config_toml, tiny_eval_session


def _modes(root: Path) -> dict[Path, tuple[int, int]]:
    """Every file and folder under ``root``: (mode bits, mtime in ns)."""
    found = {}
    for folder, dirs, files in os.walk(root):
        for name in (*dirs, *files):
            st = os.lstat(Path(folder) / name)
            found[Path(folder) / name] = (stat.S_IMODE(st.st_mode), st.st_mtime_ns)
    return found


@pytest.fixture
def umask_022():
    old = os.umask(0o022)  # the usual shell default: new files 0644, folders 0755
    yield
    os.umask(old)


@pytest.mark.slow  # about 50 s on 2 loaded cores: two tiny reconstructions and a replay
def test_nothing_a_chain_of_commands_writes_is_readable_by_group_or_others(tmp_path, umask_022):
    h5 = tiny_eval_session(tmp_path, sets=4) / "session.h5"
    (tmp_path / "tiny.toml").write_text(tiny_config_toml(3))
    before = _modes(tmp_path)
    out = tmp_path / "out"  # made by the first command, so its own mode is checked too
    chain = [
        ("reconstruct", str(h5), "--config", str(tmp_path / "tiny.toml"), "--every", "0.1s",
         "--depth-cache", str(out / "depth"), "--out", str(out / "case")),
        ("reconstruct", str(h5), "--config", str(tmp_path / "tiny.toml"), "--at", "2.0",
         "--depth-cache", str(out / "depth"), "--out", str(out / "one")),
        ("case", "export", str(out / "case"), "--out", str(out / "export")),
        ("sim", "roles", str(h5), "--every", "0.1", "--out", str(out / "roles.toml")),
        ("replay", str(out / "case"), "--role", "surgeon", "--roles", str(out / "roles.toml"),
         "--out", str(out / "video" / "surgeon.mp4"), "--size", "160x100", "--pip"),
        ("session", "export-frames", str(h5), "--out", str(out / "frames"), "--sets", "0:2"),
    ]  # fmt: skip
    stderr = {}
    for args in chain:
        done = run_egosurg(*args, timeout=300)
        assert done.returncode == 0, f"{args[:2]}: {done.stderr[-3000:]}"
        stderr[args[0]] = done.stderr
    model = next((out / "one").glob("t*/splats.ply"))
    sensor = RigCalibration.read(model.parent / "calibration.toml").sensors[0].name
    done = run_egosurg("render", str(model), "--camera", sensor, "--out", str(out / "view.png"))
    assert done.returncode == 0, done.stderr[-3000:]
    stderr["render"] = done.stderr

    written = {p: m for p, m in _modes(tmp_path).items() if before.get(p) != m}
    kinds = {p.suffix for p in written}
    # the chain wrote what the issue names: models, PLYs, cached depth, video, frames, logs
    assert {".ply", ".npz", ".mp4", ".png", ".txt", ".json"} <= kinds, kinds
    assert out in written and len(written) > 40, sorted(map(str, written))
    wide = {
        str(p.relative_to(tmp_path)): oct(mode) for p, (mode, _) in written.items() if mode & 0o077
    }
    assert not wide, f"readable by group or others: {wide}"
    for command in ("case", "replay", "session", "render"):
        assert "wrote plaintext" in stderr[command] and "owner-only" in stderr[command], command
    assert "wrote plaintext" not in stderr["reconstruct"]


def test_an_export_over_an_older_readable_file_narrows_it(tmp_path, umask_022):
    """A file opened for writing keeps its old mode, whatever the umask: an export over a
    frame an earlier run left 0644 must narrow it."""
    from tests.protocol.test_session import _write_session

    h5 = tmp_path / "s.h5"
    _write_session(h5, rows=4)
    out = tmp_path / "frames"
    args = ("session", "export-frames", str(h5), "--out", str(out), "--sets", "0:1")
    raw = ("--camera", "103")  # the session's one camera of real (raw) images
    first = run_egosurg(*args, *raw)
    assert first.returncode == 0, first.stderr
    pngs = sorted(out.rglob("*.png"))
    assert pngs
    for p in pngs:
        p.chmod(0o644)  # as an export made before owner-only outputs left it
    again = run_egosurg(*args, *raw)
    assert again.returncode == 0, again.stderr
    assert "wrote plaintext" in again.stderr
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in pngs} == {"0o600"}
