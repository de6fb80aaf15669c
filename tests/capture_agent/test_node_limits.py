"""A node's frames are held to what the node said it is: the pieces, with real frame messages,
a real camera table, accounting and session file (the processes and sockets are
tests/e2e/test_node_limits.py's). What an operator relies on: a counter that jumps by 1e12 is a
reconnect, not 1e12 dropped frames; a stamp that goes back is refused (so ``verify`` does not call
the file broken); a burst is refused beyond 1.5x the camera's rate while a healthy backlog is
not; the disk check plans with the configured rate, not a burst's."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture_agent.recorder.accounting import StreamAccounting
from capture_agent.recorder.budget import BURST_S, RATE_CAP_FACTOR, StreamLimits
from capture_agent.recorder.intake import CameraTable
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.sync import SyncConfig, Synchroniser
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.formats.sealing_config import RigSealingConfig
from protocol.formats.security_config import RigSecurityConfig
from protocol.session import CameraInfo, EventKind, GapKind, SessionReader, SessionWriter
from tests.helpers import frame_message

FPS = 30.0
P_NS = int(1e9 / FPS)
T0 = 1_700_000_000_000_000_000
JPEG = b"\xff\xd8" + bytes(2000) + b"\xff\xd9"
JUMP = 10**12


def _table(tmp_path: Path) -> CameraTable:
    return CameraTable(
        RigConfig(
            rig_name="limits",
            fps=FPS,
            control_bind="tcp://127.0.0.1:3",
            output_dir=str(tmp_path),
            agents=(
                AgentEndpoint(
                    node_id="n0",
                    frames="tcp://127.0.0.1:1",
                    control="tcp://127.0.0.1:2",
                    cameras=(11, 12),
                ),
            ),
            require_ptp_lock=False,
            security=RigSecurityConfig(insecure=True),
            sealing=RigSealingConfig(plaintext=True),
        )
    )


def test_a_1e12_index_jump_is_a_reconnect_with_sane_totals():
    acc = StreamAccounting(fps=FPS)
    gaps = []
    for k in range(10):
        gaps += acc.observe(11, k, k, T0 + k * P_NS, "n0")
    gaps += acc.observe(11, JUMP, 10, T0 + 10 * P_NS, "n0")  # a buggy or forged counter
    for k in range(11, 20):
        gaps += acc.observe(11, JUMP + k - 10, k, T0 + k * P_NS, "n0")
    t = acc.totals()[11]
    assert (t.frames_missing, t.frames_dropped_camera, t.transport_lost) == (0, 0, 0)
    assert t.reconnects == 1
    assert [(g.kind, g.missing_count, g.first_missing_frame_index) for g in gaps] == [
        (GapKind.RECONNECT, 0, -1)
    ]
    notes = acc.take_notes()
    assert [n[0] for n in notes] == [EventKind.IMPLAUSIBLE_JUMP]
    assert "frame_index jumped from 9 to 1000000000000" in notes[0][3]


def test_a_1e12_seq_jump_is_a_reconnect_not_lost_messages():
    acc = StreamAccounting(fps=FPS)
    gaps = []
    for k in range(10):
        gaps += acc.observe(11, k, k, T0 + k * P_NS, "n0")
    for k in range(10, 20):  # the node's seq jumps; the camera's index goes on
        gaps += acc.observe(11, k, JUMP + k, T0 + k * P_NS, "n0")
    assert acc.transport_lost_by_node() == {"n0": 0}
    assert [g.kind for g in gaps] == [GapKind.RECONNECT]
    assert gaps[0].missing_count == 0
    assert acc.totals()[11].frames_missing == 0
    assert [n[0] for n in acc.take_notes()] == [EventKind.IMPLAUSIBLE_JUMP]


def test_a_publisher_restarted_or_replaced_mid_take_is_noted():
    """The node's seq starts again (a new publisher with the node's key): each camera
    reconnects, and the change is noted for the session's events."""
    acc = StreamAccounting(fps=FPS)
    for k in range(10):
        acc.observe(11, k, 100 + k, T0 + k * P_NS, "n0")
    gaps = acc.observe(11, 10, 0, T0 + 10 * P_NS, "n0")
    assert [g.kind for g in gaps] == [GapKind.RECONNECT]
    notes = acc.take_notes()
    assert [(n[0], n[1], n[2]) for n in notes] == [(EventKind.PUBLISHER_CHANGED, "n0", -1)]


def test_a_plausible_gap_is_still_counted_as_drops():
    """An hour of frames is the line: just under it is a gap of dropped frames."""
    acc = StreamAccounting(fps=FPS)
    acc.observe(11, 0, 0, T0, "n0")
    step = int(3600 * FPS) - 1
    gaps = acc.observe(11, step + 1, 1, T0 + 3600 * 10**9, "n0")
    assert GapKind.FRAME_INDEX_GAP in [g.kind for g in gaps]
    assert acc.totals()[11].frames_missing == step
    assert acc.take_notes() == []


def test_stamps_that_go_back_or_repeat_are_refused_and_counted(tmp_path):
    table = _table(tmp_path)
    seen = []
    table.on_refused = lambda msg, why, detail: seen.append((why, msg.node_id, msg.camera_serial))
    now = T0
    stamps = [now, now + P_NS, now + P_NS - 1_000_000, now + P_NS, now + 2 * P_NS]
    accepted = [
        table.accept_frame(frame_message("n0", 11, k, k, s, JPEG), now + 3 * P_NS)
        for k, s in enumerate(stamps)
    ]
    assert accepted == [True, True, False, False, True]
    assert table.cameras[11].refused[EventKind.STAMP_BACKWARDS] == 2
    assert seen == [(EventKind.STAMP_BACKWARDS, "n0", 11)] * 2


def test_a_burst_is_capped_at_one_and_a_half_times_the_rate(tmp_path):
    """1000 frames within one second (stamps 1 ms apart): a second of burst at the cap and the
    cap's rate pass, the rest is refused and counted; the other camera is untouched."""
    table = _table(tmp_path)
    seen = []
    table.on_refused = lambda msg, why, detail: seen.append(why)
    ok = 0
    for k in range(1000):
        stamp = T0 + k * 1_000_000
        ok += table.accept_frame(frame_message("n0", 11, k, k, stamp, JPEG), stamp)
    cap = RATE_CAP_FACTOR * FPS
    assert cap * BURST_S <= ok <= cap * BURST_S + cap * 1.0 + 1
    assert table.cameras[11].refused[EventKind.RATE_CAPPED] == 1000 - ok
    assert seen == [EventKind.RATE_CAPPED] * (1000 - ok)
    for k in range(30):  # camera 12 at its rate meanwhile: nothing refused
        stamp = T0 + k * P_NS
        assert table.accept_frame(frame_message("n0", 12, k, 1000 + k, stamp, JPEG), stamp)


def test_a_backlog_arriving_at_once_is_not_refused(tmp_path):
    """Frames queued in the link (a recorder that paused 5 s) arrive together with their real
    stamps, one period apart: all are accepted."""
    table = _table(tmp_path)
    arrival = T0 + int(5.5e9)
    for k in range(int(5 * FPS)):
        msg = frame_message("n0", 11, k, k, T0 + k * P_NS, JPEG)
        assert table.accept_frame(msg, arrival), f"frame {k} of the backlog refused"


def test_stamps_ahead_of_the_clock_gain_no_rate(tmp_path):
    """A sender stamping up to max_clock_skew_s ahead gets its tokens by the recorder's clock
    (plus half a second), not by its own stamps."""
    table = _table(tmp_path)
    ok = 0
    for k in range(1000):  # 1000 frames in 0.1 s of the recorder's clock, stamped 5 ms apart
        rx = T0 + k * 100_000
        ok += table.accept_frame(frame_message("n0", 11, k, k, rx + k * 5_000_000, JPEG), rx)
    cap = RATE_CAP_FACTOR * FPS
    assert ok <= cap * (BURST_S + 0.5 + 0.1) + 1


def test_the_byte_budget_refuses_frames_larger_than_the_mode(tmp_path):
    """Frames at the camera's rate, each 20 times its mode's largest: after the bucket's second
    of budget, most are refused for their bytes."""
    table = _table(tmp_path)
    largest = 2 * 8 * 4 * 3
    table.set_limits(11, StreamLimits(fps=FPS, largest_frame_bytes=largest))
    big = b"\xff\xd8" + bytes(10 * largest - 4) + b"\xff\xd9"
    ok = sum(
        table.accept_frame(frame_message("n0", 11, k, k, T0 + k * P_NS, big), T0 + k * P_NS)
        for k in range(300)
    )
    budget = RATE_CAP_FACTOR * FPS * largest * (BURST_S + 300 / FPS)
    assert ok <= budget / (20 * largest) + 1
    assert table.cameras[11].refused[EventKind.BYTES_CAPPED] == 300 - ok


def test_the_disk_check_plans_with_the_configured_rate_not_a_burst(tmp_path):
    table = _table(tmp_path)
    for k in range(1000):  # a burst of 1000 frames/s
        stamp = T0 + k * 1_000_000
        table.accept_frame(frame_message("n0", 11, k, k, stamp, JPEG), stamp)
    frame_bytes = 2 * len(JPEG)
    assert table.planned_byte_rate((11,)) == FPS * frame_bytes


def _recording(tmp_path: Path, write_queue_bytes: int) -> Recording:
    infos = [
        CameraInfo(camera_serial=s, node_id="n0", resolution="TINY", width=8, height=4,
                   fps_nominal=FPS, encoding="jpeg")
        for s in (11, 12)
    ]  # fmt: skip
    writer = SessionWriter(
        tmp_path / "take.h5",
        session_name="take",
        case_metadata={},
        cameras=infos,
        tolerance_ns=P_NS // 2,
        software_version="test",
        started_unix_ns=T0,
    )
    return Recording(
        writer=writer,
        sync=Synchroniser(SyncConfig(camera_serials=(11, 12), fps=FPS, max_wait_ns=10**12)),
        accounting=StreamAccounting(fps=FPS),
        case="take",
        started_unix_ns=T0,
        started_monotonic=0.0,
        serials=(11, 12),
        write_queue_bytes=write_queue_bytes,
    )


def test_one_camera_cannot_take_the_write_queue_from_the_others(tmp_path):
    """The writer is held (as by a stalled disk) while camera 11 floods: it fills its share
    and no more, and camera 12's frames still fit."""
    rec = _recording(tmp_path, write_queue_bytes=200 * 2 * len(JPEG))
    with rec.queue._cv:  # the writer thread cannot take a job while this is held
        for k in range(1000):
            stamp = T0 + k * P_NS
            rec.write_frame(frame_message("n0", 11, k, k, stamp, JPEG), stamp)
        for k in range(20):
            stamp = T0 + k * P_NS + 1000
            rec.write_frame(frame_message("n0", 12, k, 1000 + k, stamp, JPEG), stamp)
        flooded = rec.not_written_disk_stalled[11]
        assert rec.not_written_disk_stalled[12] == 0
    assert flooded >= 1000 - 101  # its share: half the queue, one frame past it at most
    summary = rec.finish("stopped by request", {})
    assert summary["cameras"]["12"]["frames"] == 20
    with SessionReader(tmp_path / "take.h5") as r:
        assert r.verify() == []
        assert np.all(np.diff(r.frame_table(11)["capture_unix_ns"]) > 0)


def test_refused_frames_are_counted_as_refused_not_as_drops_or_losses(tmp_path):
    """A burst and a stamp that goes back, through the camera table into a take: the file's
    stamps increase, and the summary counts the refused frames as refused, none as dropped by
    the camera or lost in transport."""
    table = _table(tmp_path)
    rec = _recording(tmp_path, write_queue_bytes=64 << 20)
    table.on_refused = rec.refused_frame
    seq = 0
    sent = {11: 0, 12: 0}
    for k in range(600):  # 2 s of camera 12 at its rate; camera 11 at 10x it
        for serial in (11, 12) if k % 10 == 0 else (11,):
            back = serial == 12 and k == 300  # one stamp 1 ms before the camera's last
            stamp_k = T0 + (k - 10 if back else k) * P_NS // 10 - (1_000_000 if back else 0)
            msg = frame_message("n0", serial, sent[serial], seq, stamp_k, JPEG)
            if table.accept_frame(msg, stamp_k):
                rec.write_frame(msg, stamp_k)
            seq, sent[serial] = seq + 1, sent[serial] + 1
    summary = rec.finish("stopped by request", {})
    refused_11 = table.cameras[11].refused[EventKind.RATE_CAPPED]
    assert refused_11 > 300
    c11, c12 = summary["cameras"]["11"], summary["cameras"]["12"]
    assert (c11["dropped"], c11["transport_lost"]) == (0, 0)
    assert c11["refused"] == refused_11
    assert c11["frames"] + c11["refused"] == sent[11]
    assert (c12["dropped"], c12["transport_lost"], c12["refused"]) == (0, 0, 1)
    assert summary["events"] == {"rate_capped": refused_11, "stamp_backwards": 1}
    with SessionReader(tmp_path / "take.h5") as r:
        assert r.verify() == []
        events = r.events()
    assert sum(e.count for e in events if e.kind == EventKind.RATE_CAPPED) == refused_11
