"""Drop and gap accounting against streams with known truth (sim/timing.py)."""

from __future__ import annotations

import numpy as np
import pytest

from capture_agent.recorder.accounting import (
    MEDIAN_MIN_SAMPLES,
    NO_FRAME_INDEX,
    StreamAccounting,
    gap_record,
)
from protocol.session import GapKind, GapRecord
from sim.timing import ClockSpec, FrameClock, FrameTruth
from tests.helpers import frame_message

FPS = 30.0
P_NS = round(1e9 / FPS)
NODES = {"orin-a": (41000001, 41000002), "orin-b": (41000003, 41000004)}
SPEC = ClockSpec(fps=FPS, jitter_ns_std=150_000.0, drop_probability=0.05)

Msg = tuple[int, int, int, int, str]  # (capture_unix_ns, serial, frame_index, seq, node_id)


def _truths(seed: int = 3, seconds: float = 60.0) -> dict[int, FrameTruth]:
    return {
        s: FrameClock(SPEC, seed, s).frames(0.0, seconds) for cams in NODES.values() for s in cams
    }


def _published(truths: dict[int, FrameTruth]) -> list[Msg]:
    """What the agents publish: the frames that left the cameras, seq per node in time order."""
    out: list[Msg] = []
    for node_id, cams in NODES.items():
        frames = sorted(
            (int(t), s, int(i))
            for s in cams
            for t, i, d in zip(
                truths[s].capture_unix_ns, truths[s].frame_index, truths[s].dropped, strict=True
            )
            if not d
        )
        out += [(t, s, i, seq, node_id) for seq, (t, s, i) in enumerate(frames)]
    return sorted(out)


def _feed(acc: StreamAccounting, msgs: list[Msg]) -> list[GapRecord]:
    records: list[GapRecord] = []
    for t, s, i, seq, node in msgs:
        records += acc.observe(s, i, seq, t, node)
    return records


def _drop_runs(truth: FrameTruth) -> list[tuple[int, int]]:
    """(first index, length) of each run of dropped frames between the first and last kept."""
    kept = np.flatnonzero(~truth.dropped)
    runs: list[tuple[int, int]] = []
    for i in range(int(kept[0]) + 1, int(kept[-1])):
        if truth.dropped[i]:
            if runs and runs[-1][0] + runs[-1][1] == i:
                runs[-1] = (runs[-1][0], runs[-1][1] + 1)
            else:
                runs.append((i, 1))
    return runs


@pytest.fixture(scope="module")
def truths() -> dict[int, FrameTruth]:
    return _truths()


def test_camera_drops_match_the_truth_exactly(truths):
    acc = StreamAccounting()
    records = _feed(acc, _published(truths))
    totals = acc.totals()
    assert not [r for r in records if r.kind in (GapKind.SEQ_GAP, GapKind.RECONNECT)]
    for serial, truth in truths.items():
        runs = _drop_runs(truth)
        assert sum(n for _, n in runs) > 30  # the test has teeth: 5 % of 1800 frames
        mine = [r for r in records if r.camera_serial == serial]
        index_gaps = [r for r in mine if r.kind == GapKind.FRAME_INDEX_GAP]
        assert [(r.first_missing_frame_index, r.missing_count) for r in index_gaps] == runs
        for r in index_gaps:  # start/end are the stamps of the frames around the gap
            assert r.start_unix_ns == truth.capture_unix_ns[r.first_missing_frame_index - 1]
            assert (
                r.end_unix_ns
                == truth.capture_unix_ns[r.first_missing_frame_index + r.missing_count]
            )
        # every drop also shows as a time gap (once the running median has MEDIAN_MIN_SAMPLES
        # intervals), reported but not counted twice
        kept_index = truth.frame_index[~truth.dropped]
        judged = [
            r
            for r in index_gaps
            if np.sum(kept_index < r.first_missing_frame_index) > MEDIAN_MIN_SAMPLES
        ]
        assert len(judged) >= len(index_gaps) - 2
        time_gaps = [r for r in mine if r.kind == GapKind.TIME_GAP]
        assert [(r.start_unix_ns, r.end_unix_ns, r.missing_count) for r in time_gaps] == [
            (r.start_unix_ns, r.end_unix_ns, r.missing_count) for r in judged
        ]
        t = totals[serial]
        assert t.frames_dropped_camera == sum(n for _, n in runs) == t.frames_missing
        assert t.transport_lost == 0 and t.reconnects == 0
        assert t.time_gaps == len(judged)
        assert t.frames_received == int(np.sum(~truth.dropped))
    assert acc.transport_lost_by_node() == dict.fromkeys(NODES, 0)


def test_transport_losses_are_seq_gaps_and_not_camera_drops(truths):
    msgs = _published(truths)
    drops = {
        n: np.sort(np.concatenate([truths[s].capture_unix_ns[truths[s].dropped] for s in cams]))
        for n, cams in NODES.items()
    }
    # lose isolated messages far (> 0.1 s) from any drop of their node's cameras, so the
    # attribution is unambiguous
    lost: list[Msg] = []
    last_lost = dict.fromkeys(NODES, -(10**19))
    for m in msgs[50:-50:17]:
        t, node = m[0], m[4]
        near = np.searchsorted(drops[node], [t - 100_000_000, t + 100_000_000])
        if near[0] == near[1] and t - last_lost[node] > 100_000_000:
            lost.append(m)
            last_lost[node] = t
    assert len(lost) > 20
    lost_set = set(lost)
    kept = [m for m in msgs if m not in lost_set]
    acc = StreamAccounting()
    records = _feed(acc, kept)
    seq_gaps = [r for r in records if r.kind == GapKind.SEQ_GAP]
    assert len(seq_gaps) == len(lost)
    assert all(
        r.missing_count == 1 and r.first_missing_frame_index == NO_FRAME_INDEX for r in seq_gaps
    )
    # filed against the node's next received frame after the gap
    for r in seq_gaps:
        nxt = next(m for m in kept if m[0] == r.end_unix_ns)
        assert r.camera_serial == nxt[1]
    by_node = {n: sum(m[4] == n for m in lost) for n in NODES}
    assert acc.transport_lost_by_node() == by_node
    totals = acc.totals()
    for serial, truth in truths.items():
        mine = sum(m[1] == serial for m in lost)
        dropped = sum(n for _, n in _drop_runs(truth))
        assert totals[serial].transport_lost == mine
        assert totals[serial].frames_dropped_camera == dropped
        assert totals[serial].frames_missing == dropped + mine
        # the index gap names exactly the lost frame
        gaps = {
            (r.first_missing_frame_index, r.missing_count)
            for r in records
            if r.camera_serial == serial and r.kind == GapKind.FRAME_INDEX_GAP
        }
        assert {(m[2], 1) for m in lost if m[1] == serial} <= gaps


def _alternating(n: int, node: str = "a", cams: tuple[int, int] = (1, 2)) -> list[Msg]:
    """Two cameras of one node, frame i of both at i * P, published A then B."""
    out: list[Msg] = []
    for i in range(n):
        for k, s in enumerate(cams):
            out.append((10**18 + i * P_NS + k * 1000, s, i, 2 * i + k, node))
    return out


def test_a_lost_message_of_the_other_camera_is_charged_to_that_camera():
    msgs = _alternating(20)
    lost = msgs[21]  # camera 2, frame 10
    assert lost[1:3] == (2, 10)
    acc = StreamAccounting()
    records = _feed(acc, [m for m in msgs if m != lost])
    seq_gap = [r for r in records if r.kind == GapKind.SEQ_GAP]
    assert seq_gap == [gap_record(1, GapKind.SEQ_GAP, NO_FRAME_INDEX, 1, msgs[20][0], msgs[22][0])]
    index_gap = [r for r in records if r.kind == GapKind.FRAME_INDEX_GAP]
    assert index_gap == [gap_record(2, GapKind.FRAME_INDEX_GAP, 10, 1, msgs[19][0], msgs[23][0])]
    t = acc.totals()
    assert (t[1].frames_missing, t[1].transport_lost, t[1].frames_dropped_camera) == (0, 0, 0)
    assert (t[2].frames_missing, t[2].transport_lost, t[2].frames_dropped_camera) == (1, 1, 0)


def test_a_lost_burst_across_both_cameras_and_a_camera_drop_are_told_apart():
    msgs = _alternating(30)
    burst = set(msgs[20:24])  # frames 10 and 11 of both cameras lost in transport
    camera_drop = msgs[41]  # camera 2 frame 20 never published: seq continues without it
    kept = [m for m in msgs if m not in burst and m != camera_drop]
    renumbered = [(t, s, i, seq if seq < 41 else seq - 1, n) for t, s, i, seq, n in kept]
    acc = StreamAccounting()
    _feed(acc, renumbered)
    t = acc.totals()
    assert (t[1].frames_missing, t[1].transport_lost, t[1].frames_dropped_camera) == (2, 2, 0)
    assert (t[2].frames_missing, t[2].transport_lost, t[2].frames_dropped_camera) == (3, 2, 1)
    assert acc.transport_lost_by_node() == {"a": 4}


def test_agent_restart_is_a_reconnect_not_a_negative_gap():
    first = _alternating(50)
    later = [(t + 10 * 10**9, s, i, seq, n) for t, s, i, seq, n in _alternating(50)]
    acc = StreamAccounting()
    records = _feed(acc, first + later)
    assert [r.kind for r in records] == [GapKind.RECONNECT, GapKind.RECONNECT]
    assert [r.camera_serial for r in records] == [1, 2]
    assert all(r.first_missing_frame_index == NO_FRAME_INDEX for r in records)
    assert all(r.missing_count == 0 and r.end_unix_ns > r.start_unix_ns for r in records)
    for t in acc.totals().values():
        assert t.reconnects == 1 and t.frames_missing == 0 and t.time_gaps == 0
        assert t.frames_received == 100
    assert acc.transport_lost_by_node() == {"a": 0}


def test_agent_restart_with_camera_counters_that_continue():
    msgs = _alternating(40)
    gone = set(msgs[40:60])  # frames 20..29 never seen: the agent was down
    after = [(t, s, i, seq - 60, n) for t, s, i, seq, n in msgs[60:]]  # seq restarts at 0
    acc = StreamAccounting()
    records = _feed(acc, [m for m in msgs[:40] if m not in gone] + after)
    assert [
        (r.kind, r.camera_serial, r.first_missing_frame_index, r.missing_count) for r in records
    ] == [
        (GapKind.RECONNECT, 1, 20, 10),
        (GapKind.RECONNECT, 2, 20, 10),
    ]
    assert all(t.frames_dropped_camera == 0 for t in acc.totals().values())


def test_camera_reopen_resets_its_frame_index():
    msgs = _alternating(30)
    # camera 2 is reopened by the agent after its frame 14: its index restarts at 0
    reopened = [(t, s, i - 15 if s == 2 and i >= 15 else i, seq, n) for t, s, i, seq, n in msgs]
    acc = StreamAccounting()
    records = _feed(acc, reopened)
    assert [(r.kind, r.camera_serial) for r in records] == [(GapKind.RECONNECT, 2)]
    assert acc.totals()[1].reconnects == 0
    assert acc.totals()[2].frames_missing == 0


def test_time_gap_without_index_gap():
    msgs = _alternating(60, cams=(1, 2))
    stalled = [
        (t + 200_000_000 if s == 1 and i >= 30 else t, s, i, seq, n) for t, s, i, seq, n in msgs
    ]
    stalled.sort(key=lambda m: m[3])
    acc = StreamAccounting()
    records = _feed(acc, stalled)
    gaps = [r for r in records if r.camera_serial == 1]
    assert len(gaps) == 1 and gaps[0].kind == GapKind.TIME_GAP
    assert gaps[0].missing_count == 6  # 233 ms between frames: 6 frame slots passed
    assert gaps[0].first_missing_frame_index == 30
    t = acc.totals()[1]
    assert t.time_gaps == 1 and t.frames_dropped_camera == 0 and t.frames_missing == 0


def test_jitter_alone_makes_no_time_gap():
    spec = ClockSpec(fps=FPS, jitter_ns_std=2_000_000.0, drop_probability=0.0)
    truth = FrameClock(spec, 1, 7).frames(0.0, 30.0)
    acc = StreamAccounting()
    records: list[GapRecord] = []
    for seq, (t, i) in enumerate(zip(truth.capture_unix_ns, truth.frame_index, strict=True)):
        records += acc.observe(7, int(i), seq, int(t), "n")
    assert records == []


# -- one count of cameras missing in sets, in every report of a session ----------------------


def test_stop_summary_session_info_and_summary_count_missing_members_alike(tmp_path):
    """An operator reads 'missing-in-sets' in the stop summary, in 'egosurg session info' and in
    the file's /summary: all three count the sets in the file without a frame of the camera.

    Camera 12 loses frame 20 (one set of the take lacks it) and stops one frame before camera 11
    (the last window holds camera 11 alone: a partial window the take trims, so no set at all).
    """
    from capture_agent.operator.session_cli import summarise
    from capture_agent.recorder.recording import Recording
    from capture_agent.recorder.sync import SyncConfig, Synchroniser
    from protocol.session import CameraInfo, SessionReader, SessionWriter

    serials, jpeg = (11, 12), b"\xff\xd8" + bytes(64) + b"\xff\xd9"
    t0 = 1_700_000_000_000_000_000
    infos = [
        CameraInfo(camera_serial=s, node_id="n0", resolution="SVGA", width=8, height=4,
                   fps_nominal=FPS, encoding="jpeg")
        for s in serials
    ]  # fmt: skip
    writer = SessionWriter(
        tmp_path / "take.h5",
        session_name="take",
        case_metadata={},
        cameras=infos,
        tolerance_ns=P_NS // 2,
        rig_config_text="",
        software_version="test",
        started_unix_ns=t0,
    )
    rec = Recording(
        writer=writer,
        sync=Synchroniser(SyncConfig(camera_serials=serials, fps=FPS, max_wait_ns=10**12)),
        accounting=StreamAccounting(),
        case="take",
        started_unix_ns=t0,
        started_monotonic=0.0,
        serials=serials,
    )
    seq = 0
    for k in range(41):
        for serial, offset_ns in ((11, 0), (12, 2_000_000)):
            if serial == 12 and k in (20, 40):
                continue
            cap = t0 + k * P_NS + offset_ns
            rec.write_frame(frame_message("n0", serial, k, seq, cap, jpeg), cap)
            seq += 1
    stop = rec.finish("stopped by request", {})
    with SessionReader(tmp_path / "take.h5") as reader:
        info = {c["serial"]: c["missing_in_sets"] for c in summarise(reader)["cameras"]}
        stored = reader.summary()
        sets = reader.sets()
    truth = {11: 0, 12: 1}  # frame 20 of camera 12; the trimmed last window is not a set
    assert sets.members.shape == (40, 2)  # windows 0..39; window 40 (camera 11 alone) trimmed
    assert {int(s): c["missing_in_sets"] for s, c in stop["cameras"].items()} == truth
    assert info == truth
    assert {s: stored[str(s)]["missing_in_sets"] for s in serials} == truth
    assert {int(s): c["missing_in_sets"] for s, c in stored["extra"]["cameras"].items()} == truth
