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


def test_a_sim_rigs_recording_gets_the_eyes_its_looping_pictures_show(tmp_path):
    """A sim rig's sim time 0 is when it was deployed, and it loops its prerendered content,
    changing the picture once a second: its recordings say so (``SimRigFiles.sim_metadata``),
    and the roles are the true eyes of the moment each picture shows, not of the rig's clock."""
    from sim.world import World

    epoch = SIM_EPOCH_UNIX_NS + 86_400 * 10**9  # deployed a day after the sim epoch
    start = epoch + 100 * 10**9  # recording started 100 s later
    session = one_camera_session(
        tmp_path / "rig.h5", name="rig", started_unix_ns=start,
        set_unix_ns=[start + k * 500_000_000 for k in range(12)],  # 0-5.5 s, every 0.5 s
        metadata={"source": "egosurg sim rig", "seed": "3", "phase": "intraoperative",
                  "sim_epoch_unix_ns": str(epoch), "sim_fps": "15.0",
                  "sim_content_fps": "1.0", "sim_prerender_s": "6.0"},
    )  # fmt: skip
    out = tmp_path / "roles.toml"
    done = run_egosurg("sim", "roles", str(session), "--every", "0.5", "--out", str(out))
    assert done.returncode == 0, done.stderr
    world = World.from_seed(3, phase="intraoperative")
    surgeon = next(r for r in read_trajectories(out) if r.name == "surgeon")
    for key in surgeon.keyframes:
        # case time t is rig time 100 + t; 6 pictures a second apart loop: picture
        # floor(100 + t) mod 6, which shows sim second floor(100 + t) mod 6
        shown_s = float(int(100 + key.time_s) % 6)
        want = world.head_poses(shown_s)["surgeon"].centre_m
        assert max(abs(a - b) for a, b in zip(key.eye_m, want, strict=True)) < 1e-6, key.time_s
