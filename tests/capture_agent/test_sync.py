"""The synchroniser against the ground truth of free-running sim clocks (sim/timing.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from capture_agent.errors import SyncError
from capture_agent.recorder.sync import (
    MISSING,
    SyncConfig,
    SyncedSet,
    Synchroniser,
    group_offline,
    unassigned_offline,
)
from protocol.errors import ConfigError
from sim.timing import ClockSpec, FrameClock, FrameTruth

SERIALS = (41000001, 41000002, 41000003, 41000004)
FPS = 30.0
P_NS = 1e9 / FPS
HALF_NS = P_NS / 2
JITTER_NS = 150_000.0
SPEC = ClockSpec(fps=FPS, jitter_ns_std=JITTER_NS, drop_probability=0.05)
SEED = 7
MAX_WAIT_NS = 500_000_000
SPEC_EPOCH = FrameClock(SPEC, 0, 0).epoch_unix_ns

Event = tuple[int, int, int, int]  # (arrival_unix_ns, serial, capture_unix_ns, handle)


def _clocks(seed: int = SEED) -> dict[int, FrameClock]:
    return {s: FrameClock(SPEC, seed, s) for s in SERIALS}


def _received(truth: FrameTruth) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, frame indices) of the frames that left the camera."""
    keep = ~truth.dropped
    return truth.capture_unix_ns[keep], truth.frame_index[keep]


def _arrivals(stamps: dict[int, np.ndarray], seed: int) -> list[Event]:
    """Random latency per frame (5..120 ms), in order per camera, interleaved across cameras."""
    rng = np.random.default_rng(seed)
    events: list[Event] = []
    for serial, st in stamps.items():
        arrive = np.maximum.accumulate(st + rng.integers(5_000_000, 120_000_000, st.size))
        events += [(int(arrive[i]), serial, int(st[i]), i) for i in range(st.size)]
    events.sort()
    return events


def _random_interleave(stamps: dict[int, np.ndarray], seed: int) -> list[Event]:
    """Arrival order drawn uniformly among the cameras that still have frames."""
    rng = np.random.default_rng(seed)
    nxt = dict.fromkeys(stamps, 0)
    events: list[Event] = []
    while True:
        open_ = [s for s in stamps if nxt[s] < stamps[s].size]
        if not open_:
            return events
        s = open_[int(rng.integers(len(open_)))]
        i = nxt[s]
        nxt[s] += 1
        events.append((0, s, int(stamps[s][i]), i))


def _run(
    sync: Synchroniser, events: list[Event], poll: bool = False
) -> list[tuple[int, SyncedSet]]:
    """(emission time, set) for every set, polling at each arrival when asked, then flush."""
    out: list[tuple[int, SyncedSet]] = []
    for arrival, serial, capture, handle in events:
        out += [(arrival, s) for s in sync.add(serial, capture, handle, arrival)]
        if poll:
            out += [(arrival, s) for s in sync.poll(arrival)]
    last = events[-1][0] if events else 0
    out += [(last, s) for s in sync.flush()]
    return out


def _set_time_s(s: SyncedSet, clock: FrameClock) -> float:
    """A set's reference time mapped back to sim time (stamps are exposure + readout latency)."""
    return (s.set_unix_ns - clock.epoch_unix_ns - clock.spec.readout_latency_ns) / 1e9


def _nearest_index(clock: FrameClock, t_s: float) -> int:
    return round((t_s - clock.exposure_time(0)) / clock.period_s)


@pytest.fixture(scope="module")
def rig60() -> tuple[dict[int, FrameClock], dict[int, FrameTruth]]:
    clocks = _clocks()
    return clocks, {s: c.frames(0.0, 60.0) for s, c in clocks.items()}


@pytest.fixture(scope="module")
def online60(rig60):
    _, truths = rig60
    stamps = {s: _received(truths[s])[0] for s in SERIALS}
    sync = Synchroniser(SyncConfig(camera_serials=SERIALS, fps=FPS))
    sets = [s for _, s in _run(sync, _arrivals(stamps, seed=1))]
    return sync, sets, stamps


def test_every_frame_is_in_one_set_or_counted(online60):
    sync, sets, stamps = online60
    for k, serial in enumerate(SERIALS):
        used = [s.members[k] for s in sets if s.members[k] is not None]
        assert len(used) == len(set(used)), "a frame was used twice"
        n = stamps[serial].size
        assert len(used) + sync.unassigned_frames[serial] == n
        assert sync.unassigned_frames[serial] < 0.01 * n
        assert sync.late_frames[serial] == 0
    assert sync.sets_emitted == len(sets)


def test_members_match_the_truth_and_missing_marks_the_dropped_frame(rig60, online60):
    clocks, truths = rig60
    sync, sets, _ = online60
    tol_s = (HALF_NS + 4 * JITTER_NS) / 1e9
    for k, serial in enumerate(SERIALS):
        clock, truth = clocks[serial], truths[serial]
        _, received_index = _received(truth)
        assert np.array_equal(truth.frame_index, np.arange(truth.frame_index.size))
        marked_missing = set()
        for s in sets:
            t_s = _set_time_s(s, clock)
            i = _nearest_index(clock, t_s)
            if s.members[k] is None:
                if not 0 <= i < truth.dropped.size:
                    continue  # the frame is outside the recorded time range
                assert truth.dropped[i], (serial, s)
                marked_missing.add(i)
            else:
                j = int(received_index[s.members[k]])
                assert j == i, "member is not the frame exposed nearest the set's time"
                assert abs(truth.exposure_t_s[j] - t_s) <= tol_s
        # every other dropped frame sits where there is no set at all (all cameras dropped it,
        # or it is before the first / after the last set)
        set_times = np.array([_set_time_s(s, clock) for s in sets])
        for i in np.flatnonzero(truth.dropped).tolist():
            if i in marked_missing:
                continue
            nearest = np.min(np.abs(set_times - truth.exposure_t_s[i]))
            assert nearest > HALF_NS / 1e9, f"camera {serial} frame {i} dropped, not marked"
    assert sum(sync.missing_markers.values()) == sum(m is None for s in sets for m in s.members)


def test_spread_and_timeline(online60):
    _, sets, _ = online60
    for s in sets:
        present = [c for c in s.capture_unix_ns if c is not None]
        assert s.spread_ns == max(present) - min(present)
        assert all(abs(c - s.set_unix_ns) <= HALF_NS for c in present)
        assert s.member_rows() == tuple(MISSING if m is None else m for m in s.members)
        assert all((s.members[k] is None) == (s.capture_unix_ns[k] is None) for k in range(4))
    steps = np.diff([s.set_unix_ns for s in sets]) / P_NS
    # one period apart, or two where a window held no frame at all and was not emitted
    assert np.all(np.abs(steps - np.round(steps)) < 0.02)
    assert np.all((np.round(steps) >= 1) & (np.round(steps) <= 2))


@pytest.mark.parametrize("order", ["latency-1", "latency-2", "interleave"])
def test_online_equals_offline_twin(rig60, order):
    _, truths = rig60
    stamps = {s: _received(truths[s])[0] for s in SERIALS}
    if order == "interleave":
        events = _random_interleave(stamps, seed=3)
    else:
        events = _arrivals(stamps, seed=int(order[-1]) + 10)
    sync = Synchroniser(SyncConfig(camera_serials=SERIALS, fps=FPS))
    online = [s for _, s in _run(sync, events)]
    offline = group_offline(stamps, FPS)
    assert online == offline
    assert sync.unassigned_frames == unassigned_offline(stamps, offline)


def test_a_camera_drifting_across_a_window_edge_costs_only_a_few_markers():
    """Camera 3 runs 1500 ppm slow, so its phase turns round ~2.7 times in 60 s."""
    rng = np.random.default_rng(0)
    n = 1800
    base = 1_767_225_600_000_000_000
    stamps = {
        1: np.arange(n) * P_NS,
        2: 0.3 * P_NS + np.arange(n) * P_NS,
        3: 0.6 * P_NS + np.arange(n) * P_NS * (1 + 1500e-6),
    }
    stamps = {
        s: np.round(base + x + rng.normal(0, JITTER_NS, n)).astype(np.int64)
        for s, x in stamps.items()
    }
    sync = Synchroniser(SyncConfig(camera_serials=(1, 2, 3), fps=FPS))
    sets = [s for _, s in _run(sync, _arrivals(stamps, seed=5))]
    assert sets == group_offline(stamps, FPS)
    crossings = 3
    assert sum(sync.missing_markers.values()) <= 4 * crossings
    assert sum(sync.unassigned_frames.values()) <= 4 * crossings
    used = sum(m is not None for s in sets for m in s.members)
    assert used + sum(sync.unassigned_frames.values()) == 3 * n


def test_a_killed_camera_gets_missing_markers_and_does_not_block_the_rig(rig60):
    _, truths = rig60
    dead = SERIALS[2]
    t_kill_ns = SPEC_EPOCH + 20 * 10**9
    stamps = {s: _received(truths[s])[0] for s in SERIALS}
    stamps[dead] = stamps[dead][stamps[dead] < t_kill_ns]
    events = _arrivals(stamps, seed=4)
    sync = Synchroniser(SyncConfig(camera_serials=SERIALS, fps=FPS, max_wait_ns=MAX_WAIT_NS))
    emitted = _run(sync, events, poll=True)
    k = SERIALS.index(dead)
    after = [(when, s) for when, s in emitted if s.set_unix_ns > t_kill_ns + P_NS]
    assert len(after) > 0.9 * 40 * FPS
    assert all(s.members[k] is None for _, s in after)
    # each set leaves within max_wait (plus the largest latency) of its window's end
    lag_ns = [when - (s.set_unix_ns + HALF_NS) for when, s in emitted[:-5]]
    assert max(lag_ns) < MAX_WAIT_NS + 150_000_000
    assert dead not in sync.live_cameras
    assert sum(sync.late_frames.values()) == 0


def test_a_camera_that_starts_late_or_restarts_joins(rig60):
    _, truths = rig60
    late, restarted = SERIALS[1], SERIALS[3]
    stamps = {s: _received(truths[s])[0] for s in SERIALS}
    stamps[late] = stamps[late][stamps[late] >= SPEC_EPOCH + 10 * 10**9]
    # the restarted agent is silent from 20 to 22 s, then its camera runs with a new phase
    before = stamps[restarted][stamps[restarted] < SPEC_EPOCH + 20 * 10**9]
    again = _received(FrameClock(SPEC, SEED + 100, restarted).frames(22.0, 60.0))[0]
    stamps[restarted] = np.concatenate([before, again])
    sync = Synchroniser(SyncConfig(camera_serials=SERIALS, fps=FPS, max_wait_ns=MAX_WAIT_NS))
    sets = [s for _, s in _run(sync, _arrivals(stamps, seed=6), poll=True)]

    def presence(serial: int, t0_s: float, t1_s: float) -> float:
        k = SERIALS.index(serial)
        sel = [s for s in sets if t0_s * 1e9 <= s.set_unix_ns - SPEC_EPOCH < t1_s * 1e9]
        return sum(s.members[k] is not None for s in sel) / len(sel)

    assert presence(late, 0.0, 9.9) == 0.0
    assert presence(late, 10.2, 60.0) > 0.9
    assert presence(restarted, 20.1, 21.9) == 0.0
    assert presence(restarted, 22.5, 60.0) > 0.9
    for k, serial in enumerate(SERIALS):
        used = sum(s.members[k] is not None for s in sets)
        lost = sync.unassigned_frames[serial] + sync.late_frames[serial]
        assert used + lost == stamps[serial].size
        assert lost < 0.01 * stamps[serial].size


def test_remove_camera_unblocks_at_once():
    sync = Synchroniser(SyncConfig(camera_serials=(1, 2), fps=FPS))
    base = 10**18
    got = []
    for i in range(5):
        got += sync.add(1, base + round(i * P_NS), i)
    assert got == []  # camera 2 has not delivered: no anchor yet
    got = sync.remove_camera(2)
    assert [s.members for s in got] == [(i, None) for i in range(4)]
    assert sync.flush()[0].members == (4, None)
    assert sync.add(2, base + round(6 * P_NS), 0) == []  # it is back: sets wait for it again
    assert 2 in sync.live_cameras


def test_late_frame_after_timeout_is_counted():
    sync = Synchroniser(SyncConfig(camera_serials=(1, 2), fps=FPS, max_wait_ns=100_000_000))
    base = 10**18
    for i in range(3):
        sync.add(1, base + round(i * P_NS), i)
        sync.add(2, base + round(i * P_NS), i)
    for i in range(3, 30):
        sync.add(1, base + round(i * P_NS), i)
    out = sync.poll(base + round(29 * P_NS) + 200_000_000)
    assert len(out) >= 20 and all(s.members[1] is None for s in out[2:])
    assert sync.add(2, base + round(3 * P_NS), 3) == []  # its window is gone
    assert sync.late_frames == {1: 0, 2: 1}


def test_throughput_is_well_above_a_rig():
    """8 cameras at 120 fps for 40 s (38,400 frames) must take well under 40 s of CPU."""
    n, serials = 4800, tuple(range(1, 9))
    rng = np.random.default_rng(1)
    grid = np.round(np.arange(n) * (1e9 / 120)).astype(np.int64)
    stamps = {s: 10**18 + s * 900_000 + grid for s in serials}
    events: list[Event] = []
    for s in serials:
        arrive = np.maximum.accumulate(stamps[s] + rng.integers(0, 30_000_000, n))
        events += [(int(arrive[i]), s, int(stamps[s][i]), i) for i in range(n)]
    events.sort()
    sync = Synchroniser(SyncConfig(camera_serials=serials, fps=120.0))
    t0 = time.perf_counter()
    n_sets = 0
    for _, s, c, h in events:
        n_sets += len(sync.add(s, c, h))
    n_sets += len(sync.flush())
    elapsed = time.perf_counter() - t0
    assert n_sets == n
    assert elapsed < 4.0, f"{len(events) / elapsed:.0f} frames/s"


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"camera_serials": (1, 2), "fps": 0.0}, "fps"),
        ({"camera_serials": (1, 2), "fps": float("nan")}, "fps"),
        ({"camera_serials": (1, 2, 1), "fps": 30.0}, "more than once"),
        ({"camera_serials": (), "fps": 30.0}, "empty"),
        ({"camera_serials": (1, -2), "fps": 30.0}, "camera_serials"),
        ({"camera_serials": (1,), "fps": 30.0, "max_wait_ns": 0}, "max_wait_ns"),
    ],
)
def test_bad_config_is_refused_clearly(kwargs, needle):
    with pytest.raises(ConfigError, match=needle):
        SyncConfig(**kwargs)


def test_unknown_camera_is_refused():
    sync = Synchroniser(SyncConfig(camera_serials=(1,), fps=FPS))
    with pytest.raises(SyncError, match="not in the rig"):
        sync.add(9, 10**18, 0)
    with pytest.raises(ValueError, match="capture order"):
        group_offline({1: np.array([2, 1])}, FPS)


def test_empty_and_out_of_order_edges():
    sync = Synchroniser(SyncConfig(camera_serials=(1, 2), fps=FPS))
    assert sync.poll(10**18) == [] and sync.flush() == [] and sync.reference_unix_ns is None
    base = 10**18
    stamps = [base + round(i * P_NS) for i in range(6)]
    sets: list[SyncedSet] = []
    for i in (0, 2, 1, 3, 4, 5):  # camera 1 breaks capture order before the anchor
        sets += sync.add(1, stamps[i], i)
    for i in range(6):
        sets += sync.add(2, stamps[i] + 1000, i)
    sets += sync.flush()
    assert [s.members for s in sets] == [(i, i) for i in range(6)]
    assert [s.spread_ns for s in sets] == [1000] * 6
