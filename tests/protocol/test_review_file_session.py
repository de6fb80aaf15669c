"""Roles, trajectory, site and field files say which session they were made for (their
``[session]`` table), read back exactly; files from before the table still read; a bad table is
one clear line; and the comparison a review command makes (``check_made_for``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.formats.session_id import SessionId, SessionMismatchError, check_made_for
from protocol.formats.site import SiteBox, SiteFileError, read_site, read_site_file, site_toml
from protocol.formats.trajectory import (
    Keyframe,
    Trajectory,
    TrajectoryFileError,
    read_trajectories,
    read_trajectory_file,
    write_trajectories,
)

CASE = SessionId(name="sim-intraoperative-seed3", started_unix_ns=1_767_225_600_000_000_000)
DEMO = SessionId(name="demo-or1", started_unix_ns=1_795_856_400_000_000_000)
WALK = Trajectory(
    name="walk", keyframes=(Keyframe(time_s=2.0, eye_m=(0, 0, 1.7), look_at_m=(1, 0, 1)),)
)
MONITOR = SiteBox(name="monitor-a", centre_m=(1.0, 0.0, 1.5), size_m=(0.01, 0.6, 0.4))


def test_the_session_a_file_was_made_for_reads_back_exactly(tmp_path: Path):
    odd = SessionId(name='OR 3 "north" 2026-11-28', started_unix_ns=CASE.started_unix_ns + 1)
    path = write_trajectories(tmp_path / "roles.toml", [WALK], odd)
    assert read_trajectory_file(path).session == odd
    assert read_trajectories(path) == (WALK,)
    (tmp_path / "site.toml").write_text(site_toml([MONITOR], CASE))
    assert read_site_file(tmp_path / "site.toml") == (CASE, {"monitor-a": MONITOR})
    assert "2026-01-01 00:00:00.000 UTC" in (tmp_path / "site.toml").read_text()  # for people


def test_a_file_from_before_the_table_still_reads_and_names_no_session(tmp_path: Path):
    path = write_trajectories(tmp_path / "old.toml", [WALK])
    assert "[session]" not in path.read_text()
    assert read_trajectory_file(path).session is None
    (tmp_path / "site.toml").write_text(site_toml([MONITOR]))
    assert read_site(tmp_path / "site.toml") == {"monitor-a": MONITOR}


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("name = 'x'\nstarted_unix_ns = -5", "started_unix_ns -5 must be the session's start"),
        ("name = 'x'\nstarted_unix_ns = '2026-01-01'", "started_unix_ns"),
        ("name = 'x'\nstarted = 1", "unknown option 'session.started'"),
    ],
)
def test_a_bad_session_table_is_one_clear_line(tmp_path: Path, table: str, message: str):
    text = write_trajectories(tmp_path / "t.toml", [WALK]).read_text()
    head, tail = text.split("\n\n", 1)
    (tmp_path / "t.toml").write_text(f"{head}\n[session]\n{table}\n\n{tail}")
    with pytest.raises(TrajectoryFileError, match=message) as err:
        read_trajectories(tmp_path / "t.toml")
    assert "\n" not in str(err.value) and "t.toml" in str(err.value)
    (tmp_path / "s.toml").write_text(
        site_toml([MONITOR]).replace("\n[[boxes]]", f"\n[session]\n{table}\n[[boxes]]", 1)
    )
    with pytest.raises(SiteFileError, match=message):
        read_site(tmp_path / "s.toml")


def test_a_file_of_another_session_is_refused_naming_both_and_one_without_is_a_warning():
    with pytest.raises(SessionMismatchError) as err:
        check_made_for(DEMO, CASE, what="roles.toml", case="the case case/")
    line = str(err.value)
    assert "roles.toml was made for session 'demo-or1' started 2026-11-28 09:00:00.000 UTC" in line
    assert "case/ is of session 'sim-intraoperative-seed3' started 2026-01-01" in line
    # the simulator starts every evaluation session at its epoch: the name tells seeds apart
    other_seed = SessionId(name="sim-intraoperative-seed0", started_unix_ns=CASE.started_unix_ns)
    with pytest.raises(SessionMismatchError):
        check_made_for(other_seed, CASE, what="roles.toml", case="the case case/")
    assert check_made_for(CASE, CASE, what="roles.toml", case="the case case/") is None
    # a case whose session file is gone knows only its start: that is the whole check then
    gone = SessionId(name="", started_unix_ns=CASE.started_unix_ns)
    assert check_made_for(CASE, gone, what="roles.toml", case="the case case/") is None
    warning = check_made_for(None, CASE, what="hand.toml", case="the case case/")
    assert warning is not None and "hand.toml does not say which session" in warning


def _rewrite_forever(path: str, session: SessionId) -> None:  # runs in a child process
    long = Trajectory(
        name="long",
        keyframes=tuple(
            Keyframe(time_s=0.5 * k, eye_m=(0, 0, 1.7), look_at_m=(1, 0, 1)) for k in range(20000)
        ),
    )
    while True:
        write_trajectories(path, [WALK, long], session)


def test_a_reader_never_sees_a_roles_file_half_written(tmp_path: Path):
    """The viewer rewrites the roles file each time a reviewer names a track, while a review
    command (or the viewer's own page) may read it: a reader finds the old file or the whole new
    one, never a torn one; a file made owner-only stays so when rewritten."""
    import multiprocessing
    import time

    path = tmp_path / "roles.toml"
    write_trajectories(path, [WALK], CASE)
    path.chmod(0o600)
    writer = multiprocessing.get_context("spawn").Process(
        target=_rewrite_forever, args=(str(path), CASE), daemon=True
    )
    writer.start()
    try:
        reads, names = 0, set()
        deadline = time.monotonic() + 30
        while (len(names) < 2 or reads < 200) and time.monotonic() < deadline:
            names.add(len(read_trajectory_file(path).trajectories))  # raises on a torn file
            reads += 1
        assert names == {1, 2}, "the writer never replaced the file"
    finally:
        writer.kill()
        writer.join()
    assert path.stat().st_mode & 0o777 == 0o600
