"""``egosurg sim roles`` on a recorded session: the times it covers come from its sets."""

from __future__ import annotations

from pathlib import Path

from protocol.formats.trajectory import read_trajectories
from sim.timing import SIM_EPOCH_UNIX_NS
from tests.helpers import one_camera_session, run_egosurg


def _session(path: Path, first_set_offset_ns: int) -> Path:
    """A sim session (seed 3, intraoperative) whose first set lies ``first_set_offset_ns``
    from its start, then one set every 66.7 ms."""
    start = SIM_EPOCH_UNIX_NS + 5_000_000_000
    return one_camera_session(
        path, name="live", started_unix_ns=start,
        set_unix_ns=[start + first_set_offset_ns + k * 66_666_667 for k in range(4)],
        metadata={"seed": "3", "phase": "intraoperative"},
    )  # fmt: skip


def test_a_first_set_stamped_just_before_the_start_still_gives_roles_from_0(tmp_path):
    """A live rig's first set can be stamped a fraction of a millisecond before the session's
    start; the roles then start at 0 s rather than the command refusing the session."""
    session = _session(tmp_path / "s.h5", first_set_offset_ns=-400_000)
    out = tmp_path / "roles.toml"
    done = run_egosurg("sim", "roles", str(session), "--every", "0.1", "--out", str(out))
    assert done.returncode == 0, done.stderr
    roles = read_trajectories(out)
    assert roles and all(r.keyframes[0].time_s == 0.0 for r in roles)
    assert all(abs(r.keyframes[-1].time_s - 0.1) < 1e-9 for r in roles)  # sets end at 0.2 s
