"""The people bench's judge (bench/bench_people.py) on hand-made timestamps whose identity
switches are known by construction: CLEAR MOT's procedure (Bernardin & Stiefelhagen 2008) keeps a
person's track while it stays within 0.5 m of them, so a second track that is sometimes nearer is
no switch; the judge without that keeping step counts one each time it is nearer and one back."""

from __future__ import annotations

import numpy as np

from bench.bench_people import mismatches


def _frames(positions: list[dict[str, tuple[float, float]]], tracks: list[dict[int, tuple]]):
    return [
        ({n: np.array([*xy, 1.6]) for n, xy in truth.items()},
         [(tid, np.array([*xy, 1.6])) for tid, xy in est.items()])
        for truth, est in zip(positions, tracks, strict=True)
    ]  # fmt: skip


def test_a_second_track_sometimes_nearer_is_no_switch_but_the_nearest_match_counts_two():
    # track 1 follows A 0.2 m off all along; track 2 (a neighbour's shoulder) shows 0.05 m from A
    # at timestamps 3-4 and 7: nearer than track 1, but track 1 is still within 0.5 m of A
    n = 10
    truth = [{"A": (0.0, 0.0)}] * n
    est = [{1: (0.2, 0.0), **({2: (0.05, 0.0)} if k in (3, 4, 7) else {})} for k in range(n)]
    matched, switches = mismatches(_frames(truth, est))
    assert switches == {"A": 0}
    assert [m["A"] for m in matched] == [1] * n
    _, nearest = mismatches(_frames(truth, est), keep=False)
    assert nearest == {"A": 4}  # 1 -> 2 -> 1 twice


def test_a_track_lost_and_taken_over_is_one_switch_and_the_new_track_is_kept_after():
    # A's track 1 is lost at timestamp 4 and track 2 (0.3 m off) takes A; track 1 comes back
    # 0.1 m from A at timestamp 6: CLEAR MOT keeps track 2 (one switch), nearest goes back (two)
    n = 10
    truth = [{"A": (0.0, 0.0)}] * n
    est = [({1: (0.1, 0.0)} if k not in (4, 5) else {}) | ({2: (0.3, 0.0)} if k >= 4 else {})
           for k in range(n)]  # fmt: skip
    matched, switches = mismatches(_frames(truth, est))
    assert switches == {"A": 1}
    assert [m["A"] for m in matched] == [1] * 4 + [2] * 6
    _, nearest = mismatches(_frames(truth, est), keep=False)
    assert nearest == {"A": 2}


def test_two_people_whose_tracks_swap_as_they_pass_count_one_switch_each():
    # A walks +x and B walks -x along y = 0 and y = 0.3, crossing at timestamp 5; the tracks
    # follow them until 5, then track 1 follows B and track 2 follows A: a real swap
    truth, est = [], []
    for k in range(10):
        a, b = (-1.0 + 0.2 * k, 0.0), (1.0 - 0.2 * k, 0.3)
        truth.append({"A": a, "B": b})
        est.append({1: a, 2: b} if k < 5 else {1: b, 2: a})
    matched, switches = mismatches(_frames(truth, est))
    assert switches == {"A": 1, "B": 1}
    assert matched[9] == {"A": 2, "B": 1}


def test_a_person_unmatched_for_a_while_then_on_another_track_is_one_switch():
    # A's track 1 ends at timestamp 3; nothing within 0.5 m for 3 timestamps (a track 0.8 m off
    # does not count); then track 3 follows A: one switch, counted against the last track matched
    truth = [{"A": (0.0, 0.0)}] * 10
    est = [{1: (0.0, 0.1)} if k < 3 else {2: (0.8, 0.0)} if k < 6 else {3: (0.0, -0.1)}
           for k in range(10)]  # fmt: skip
    matched, switches = mismatches(_frames(truth, est))
    assert switches == {"A": 1}
    assert [m.get("A") for m in matched] == [1] * 3 + [None] * 3 + [3] * 4
