"""The session events table (``/events``): what happened to the links and streams during a take,
written with the recording, read back, checked by ``verify`` and listed by ``session info``;
a flood of one kind cannot fill the file, and a file written before the table still opens."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py

from capture_agent.recorder.accounting import StreamAccounting
from capture_agent.recorder.events import ROWS_PER_WINDOW
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.sync import SyncConfig, Synchroniser
from protocol.session import CameraInfo, EventKind, SessionReader, SessionWriter
from protocol.session.verify import describe_events
from tests.helpers import frame_message, run_egosurg

T0 = 1_700_000_000_000_000_000
P_NS = 33_333_333
JPEG = b"\xff\xd8" + bytes(64) + b"\xff\xd9"


def _recording(path: Path, serials: tuple[int, ...] = (11, 12)) -> Recording:
    infos = [
        CameraInfo(camera_serial=s, node_id=f"n{i}", resolution="SVGA", width=8, height=4,
                   fps_nominal=30.0, encoding="jpeg")
        for i, s in enumerate(serials)
    ]  # fmt: skip
    writer = SessionWriter(
        path,
        session_name="take",
        case_metadata={},
        cameras=infos,
        tolerance_ns=P_NS // 2,
        software_version="test",
        started_unix_ns=T0,
    )
    return Recording(
        writer=writer,
        sync=Synchroniser(SyncConfig(camera_serials=serials, fps=30.0, max_wait_ns=10**12)),
        accounting=StreamAccounting(),
        case="take",
        started_unix_ns=T0,
        started_monotonic=0.0,
        serials=serials,
    )


def _record_with_events(path: Path) -> dict:
    rec = _recording(path)
    for k in range(10):
        for serial, node in ((11, "n0"), (12, "n1")):
            cap = T0 + k * P_NS
            rec.write_frame(frame_message(node, serial, k, k, cap, JPEG), cap)
        if k == 3:
            rec.append_event(EventKind.LINK_DROPPED, "n1", -1, "no message for 2.0 s")
            rec.append_event(EventKind.LINK_RECONNECTED, "n1", -1, "after 0.4 s: keepalive")
    for _ in range(10_000):  # a flood from one node: counted, in a few rows
        rec.append_event(EventKind.STAMP_BACKWARDS, "n0", 11, "stamp 1.0 ms before the last")
    return rec.finish("stopped by request", {})


def test_events_are_written_with_the_take_read_back_and_a_flood_is_counted_in_few_rows(
    tmp_path: Path,
) -> None:
    summary = _record_with_events(tmp_path / "take.h5")
    with SessionReader(tmp_path / "take.h5") as r:
        events = r.events()
        problems = r.verify()
        described = describe_events(r)
    kinds = [e.kind for e in events]
    assert kinds[:2] == [EventKind.LINK_DROPPED, EventKind.LINK_RECONNECTED]
    assert events[0].node_id == "n1" and events[0].camera_serial == -1
    assert events[1].detail == "after 0.4 s: keepalive"
    flood = [e for e in events if e.kind == EventKind.STAMP_BACKWARDS]
    assert sum(e.count for e in flood) == 10_000  # every occurrence counted
    assert len(flood) <= 2 * (ROWS_PER_WINDOW + 1)  # in a bounded number of rows
    assert all(e.camera_serial == 11 and e.node_id == "n0" for e in flood)
    assert summary["events"] == {
        "link_dropped": 1,
        "link_reconnected": 1,
        "stamp_backwards": 10_000,
    }
    assert problems == []  # events are what happened, not damage
    assert any("stamp_backwards: 10000 time(s)" in line for line in described), described
    assert any("link_dropped: 1 time(s)" in line and "'n1'" in line for line in described)


def test_session_info_and_verify_list_the_events(tmp_path: Path) -> None:
    _record_with_events(tmp_path / "take.h5")
    info = run_egosurg("session", "info", str(tmp_path / "take.h5"), timeout=60)
    assert info.returncode == 0, info.stderr
    assert "event stamp_backwards: 10000 (n0 10000)" in info.stdout
    assert "event link_dropped: 1 (n1 1)" in info.stdout
    verify = run_egosurg("session", "verify", str(tmp_path / "take.h5"), timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    assert "event link_reconnected: 1 time(s) in 1 record(s)" in verify.stdout


def test_a_file_written_before_the_events_table_still_opens_and_verifies(tmp_path: Path) -> None:
    _record_with_events(tmp_path / "take.h5")
    old = tmp_path / "old.h5"
    shutil.copy(tmp_path / "take.h5", old)
    with h5py.File(old, "a") as f:
        del f["events"]
    with SessionReader(old) as r:
        assert r.events() == []
        assert not [p for p in r.verify() if p.startswith("error")]
    info = run_egosurg("session", "info", str(old), timeout=60)
    assert info.returncode == 0 and "event " not in info.stdout


def test_verify_reports_a_damaged_events_table(tmp_path: Path) -> None:
    _record_with_events(tmp_path / "take.h5")
    with h5py.File(tmp_path / "take.h5", "a") as f:
        f["events/kind"][0] = 200  # no such kind
        f["events/camera_serial"][1] = 99  # no such camera
        f["events/count"][2] = 0
    with SessionReader(tmp_path / "take.h5") as r:
        errors = [p for p in r.verify() if p.startswith("error")]
        kinds = {e.kind for e in r.events()}  # the unknown row is skipped, the rest read
    assert any("events 0 have an unknown kind" in p for p in errors), errors
    assert any("events 1 name a camera not in the session" in p for p in errors), errors
    assert any("events 2 stand for fewer than 1" in p for p in errors), errors
    assert EventKind.LINK_RECONNECTED in kinds
