"""Detections joined over time into tracks: one per person, by where they are and how they move.

At each timestamp every live track predicts where its head is now (last position plus its
velocity, the speed capped at ``max_speed_m_s``); detections are given to tracks by the
assignment of least total distance (``scipy.optimize.linear_sum_assignment``) within a gate
that widens with the time since the track was last seen. A detection left over starts a track
when it is confident; a track unseen for longer than ``max_gap_s`` ends; one seen too seldom or
too doubtfully is dropped at the end; a track that starts soon after another ended, near where
that one was last seen, continues it. The timestamps a live track was not seen at are its gaps:
kept, never filled in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from reconstructor.people.config import PeopleConfig
from reconstructor.people.detect import Detection

START_CONFIDENCE = 0.6  # a detection must be this sure of itself to start a track
NO_MATCH = 1e6


@dataclass
class Track:
    id: int
    times_s: list[float] = field(default_factory=list)
    detections: list[Detection] = field(default_factory=list)
    missed_s: list[float] = field(default_factory=list)  # times it was live but not seen

    @property
    def last_s(self) -> float:
        return self.times_s[-1]

    def xy(self) -> np.ndarray:
        return np.array([d.head_xy_m for d in self.detections])

    def predict(self, t_s: float, max_speed_m_s: float) -> np.ndarray:
        xy = np.asarray(self.detections[-1].head_xy_m)
        if len(self.times_s) < 2:
            return xy
        dt = self.times_s[-1] - self.times_s[-2]
        v = (xy - np.asarray(self.detections[-2].head_xy_m)) / max(dt, 1e-3)
        speed = float(np.linalg.norm(v))
        if speed > max_speed_m_s:
            v *= max_speed_m_s / speed
        return xy + v * min(t_s - self.last_s, 1.0)

    def gaps_s(self) -> list[tuple[float, float]]:
        """(last seen, seen again) around each run of missed timestamps inside the track."""
        times = np.asarray(self.times_s)
        gaps = set()
        for t in self.missed_s:
            k = int(np.searchsorted(times, t))
            if 0 < k < len(times):
                gaps.add((float(times[k - 1]), float(times[k])))
        return sorted(gaps)


def track_people(frames: list[tuple[float, list[Detection]]], config: PeopleConfig) -> list[Track]:
    """``frames``: (time, detections) in time order; the tracks seen at least
    ``min_detections`` times, numbered 1.. by when they start."""
    live: list[Track] = []
    done: list[Track] = []
    next_id = 1
    for t, detections in frames:
        still: list[Track] = []
        for tr in live:
            (still if t - tr.last_s <= config.max_gap_s else done).append(tr)
        live = still
        cost = np.full((len(live), len(detections)), NO_MATCH)
        for i, tr in enumerate(live):
            pred = tr.predict(t, config.max_speed_m_s)
            gate = min(config.gate_m + config.gate_growth_m_s * (t - tr.last_s), 1.2)
            for j, d in enumerate(detections):
                dist = float(np.hypot(*(np.asarray(d.head_xy_m) - pred)))
                if dist <= gate:
                    cost[i, j] = dist
        rows, cols = linear_sum_assignment(cost) if cost.size else ([], [])
        taken: set[int] = set()
        seen: set[int] = set()
        for i, j in zip(rows, cols, strict=True):
            if cost[i, j] < NO_MATCH:
                live[i].times_s.append(t)
                live[i].detections.append(detections[j])
                taken.add(j)
                seen.add(i)
        for i, tr in enumerate(live):
            if i not in seen:
                tr.missed_s.append(t)
        for j, d in enumerate(detections):
            if j not in taken and d.confidence >= START_CONFIDENCE:
                live.append(Track(next_id, [t], [d]))
                next_id += 1
    kept = [
        tr
        for tr in done + live
        if len(tr.times_s) >= config.min_detections
        and np.mean([d.confidence for d in tr.detections]) >= config.min_track_confidence
    ]
    kept = _stitched(sorted(kept, key=lambda tr: (tr.times_s[0], tr.id)), config)
    for k, tr in enumerate(kept, start=1):
        tr.id = k
    return kept


def _stitched(tracks: list[Track], config: PeopleConfig) -> list[Track]:
    """Tracks joined where one ends and another starts soon after, near where the first was last
    seen (a person missed for a while, not a new person): the time between becomes a gap."""
    out: list[Track] = []
    for tr in tracks:
        best, best_d = None, math.inf
        for prev in out:
            gap = tr.times_s[0] - prev.last_s
            if not 0 < gap <= config.stitch_gap_s:
                continue
            d = float(np.hypot(*(tr.xy()[0] - prev.xy()[-1])))
            if d <= config.gate_m + config.gate_growth_m_s * gap and d < best_d:
                best, best_d = prev, d
        if best is None:
            out.append(tr)
            continue
        best.missed_s.append(0.5 * (best.last_s + tr.times_s[0]))  # the gap between them
        best.times_s += tr.times_s
        best.detections += tr.detections
        best.missed_s += tr.missed_s
    return out
