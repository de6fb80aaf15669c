"""Which frames calibration reads, and the background model it detects against."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calibration.detect.background import temporal_median, temporal_median_reference
from calibration.detect.extract import ExtractConfig, choose_sets, split_runs
from calibration.errors import ExtractionError


@pytest.mark.parametrize("n_frames", [3, 4, 9, 15])
def test_the_fast_median_is_numpys(n_frames):
    rng = np.random.default_rng(n_frames)
    frames = rng.integers(0, 256, (n_frames, 37, 53, 3), dtype=np.uint8)
    assert np.array_equal(temporal_median(frames), temporal_median_reference(frames))
    assert np.array_equal(
        temporal_median(list(frames[:, :, :, 0])), temporal_median_reference(frames[:, :, :, 0])
    )


def test_the_median_background_ignores_what_passes_through():
    """A bright object crossing a third of the frames leaves no trace in the background."""
    rng = np.random.default_rng(1)
    room = rng.integers(0, 200, (40, 60, 3), dtype=np.uint8)
    frames = np.repeat(room[None], 9, axis=0)
    for k in range(4):
        frames[k, 10:20, 10 * k : 10 * k + 15] = 255
    assert np.array_equal(temporal_median(frames), room)
    with pytest.raises(ValueError, match="uint8"):
        temporal_median(frames.astype(np.float32))


def _session_times(seconds: float, fps: float) -> np.ndarray:
    return (np.arange(int(seconds * fps)) * (1e9 / fps)).astype(np.int64)


def test_a_long_session_is_read_in_runs_spread_over_all_of_it():
    times = _session_times(120.0, 30.0)  # 3600 sets
    cfg = ExtractConfig(max_sets=300, run_length=2, keep_first_s=3.0)
    chosen = choose_sets(times, cfg)
    assert len(chosen) <= 300 and np.all(np.diff(chosen) > 0)
    early = np.flatnonzero(times <= 3e9)
    assert np.isin(early, chosen).all()  # the wand on the floor: every set of the first seconds
    rest = chosen[chosen > early[-1]]
    runs = np.split(rest, np.flatnonzero(np.diff(rest) != 1) + 1)
    assert all(len(r) % 2 == 0 for r in runs)  # whole runs of two consecutive sets
    # spread evenly: every tenth of the session is read
    assert len(np.unique(chosen * 10 // len(times))) == 10
    assert chosen[-1] >= len(times) - 30


def test_a_short_session_is_read_whole():
    times = _session_times(10.0, 15.0)
    assert np.array_equal(choose_sets(times, ExtractConfig(max_sets=600)), np.arange(150))


def test_work_chunks_keep_runs_whole():
    times = _session_times(120.0, 30.0)
    chosen = choose_sets(times, ExtractConfig(max_sets=300, run_length=3))
    chunks = split_runs(chosen, 8)
    assert np.array_equal(np.concatenate(chunks), chosen)
    assert 6 <= len(chunks) <= 10
    for a, b in itertools.pairwise(chunks):
        # a cut between two chunks never falls inside a run of three, except in the long early
        # window, which is itself many runs
        if b[0] - a[-1] == 1:
            assert b[0] <= np.flatnonzero(times <= 3e9)[-1] + 1


def test_bad_extraction_settings_are_named():
    with pytest.raises(ExtractionError, match="run_length"):
        ExtractConfig(max_sets=100, run_length=40)
    with pytest.raises(ExtractionError, match="background_frames"):
        ExtractConfig(background_frames=2)
