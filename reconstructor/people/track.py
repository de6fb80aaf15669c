"""Detections joined over time into tracks: one per person, by where they are and how they move.

The track management of multi-object trackers. A detection left over starts a *tentative*
track when it is confident; the track is *confirmed* once it has been seen at ``confirm_seen``
of its first ``confirm_timestamps`` timestamps, and a tentative track that can no longer reach
that is dropped (stereo noise and a neighbour's shoulder make heads that last a timestamp or
two). A detection less sure of itself than ``match_confidence`` is given to no track (a
doubtful head between a walker and someone standing bends the walker's velocity onto them). At
each timestamp every live track predicts where its head is now (last position plus
its velocity, the speed capped at ``max_speed_m_s``); detections are given to the confirmed
tracks first, by the assignment of least total distance (``scipy.optimize.linear_sum_assignment``)
within a gate that widens with the time since the track was last seen and at the track's usual
head height (within ``height_gate_m``, each metre of difference costing ``height_weight`` metres:
people differ in height, which their scrubs do not show); a detection left over
within ``duplicate_m`` of a confirmed track's head, and not above its height, is that person
again (a shoulder, a second peak of the same head) and is dropped; what is left goes to the
tentative tracks the same way, and the rest may start new ones. A confirmed track missed by the
detector coasts for at most ``max_gap_s`` (a second: coasting longer, a track drifts onto a
neighbour), then ends; the timestamps it coasted through are its gaps, kept and never filled
in. Only confirmed tracks are reported, those seen too seldom or too doubtfully dropped, and
those with their head among the room's background cubes (equipment the background learned in
part): staying in one place with a few of them round it, or anywhere with many; after the
linking, also a track whose head sits, over its whole life, at the lowest or highest head
tops the detector allows (``edge_head_m``). The recording
is whole before tracking starts, so the tracks are then linked over the whole case: a track
that starts within ``stitch_gap_s`` after another ended, where a walker could have gone in
between, of the other's height over their whole lives, continues it, the pairs chosen by least
total cost at once (each track with at most one predecessor and one successor), and two
tracks that follow one person at the same time are joined (``reconstructor.people.merge``).
Last, a track missed for a while between two sightings (coasting, or between two tracks the
linking joined) takes the heads found on its way that no track took, however doubtful
(``fill_m``): where the person was before and after says which head is theirs; the rest of the
time stays a gap.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from reconstructor.people.config import PeopleConfig
from reconstructor.people.detect import Detection
from reconstructor.people.merge import merge_duplicates

START_CONFIDENCE = 0.6  # a detection must be this sure of itself to start a track
NO_MATCH = 1e6
TOP_WINDOW = 10  # detections a track's usual head height is taken over


@dataclass
class Track:
    id: int
    times_s: list[float] = field(default_factory=list)
    detections: list[Detection] = field(default_factory=list)
    missed_s: list[float] = field(default_factory=list)  # times it was live but not seen
    confirmed: bool = False
    age: int = 0  # timestamps since it started, the first one included

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

    def top_m(self) -> float:
        """The head top's usual height: the median over the last ``TOP_WINDOW`` detections."""
        return float(np.median([d.top_m for d in self.detections[-TOP_WINDOW:]]))

    def height_m(self) -> float:
        """The head top's height over the track's whole life (the median of all its heads): the
        person's height, which tells two tracks of one person from a neighbour's better than
        the heads near where one ends and the other starts."""
        return float(np.median([d.top_m for d in self.detections]))

    def gaps_s(self) -> list[tuple[float, float]]:
        """(last seen, seen again) around each run of missed timestamps inside the track."""
        times = np.asarray(self.times_s)
        gaps = set()
        for t in self.missed_s:
            k = int(np.searchsorted(times, t))
            if 0 < k < len(times):
                gaps.add((float(times[k - 1]), float(times[k])))
        return sorted(gaps)


def _assign(
    tracks: list[Track], detections: list[Detection], free: list[int], t: float, c: PeopleConfig
) -> dict[int, int]:
    """{track index: detection index} of least total distance, each pair within its gate."""
    cost = np.full((len(tracks), len(free)), NO_MATCH)
    for i, tr in enumerate(tracks):
        pred = tr.predict(t, c.max_speed_m_s)
        gate = min(c.gate_m + c.gate_growth_m_s * (t - tr.last_s), 1.2)
        top = tr.top_m()
        for k, j in enumerate(free):
            dist = float(np.hypot(*(np.asarray(detections[j].head_xy_m) - pred)))
            rise = abs(detections[j].top_m - top)
            if dist <= gate and rise <= c.height_gate_m:
                cost[i, k] = dist + c.height_weight * rise
    if not cost.size:
        return {}
    rows, cols = linear_sum_assignment(cost)
    return {int(i): free[k] for i, k in zip(rows, cols, strict=True) if cost[i, k] < NO_MATCH}


def coast_limit_s(times_s: list[float], max_gap_s: float) -> float:
    """How long after its last sighting a track may still take a head: ``max_gap_s``, but never
    less than one sampling interval (a track seen at the timestamp before is always live), plus
    half an interval, so that a session's timestamps, which are its sets' times and not an
    exact grid, end a track at the same timestamp as an exact grid would."""
    steps = np.diff(np.asarray(times_s, dtype=np.float64))
    step_s = float(np.median(steps)) if len(steps) else 0.0
    return max(max_gap_s, step_s) + step_s / 2


def track_people(frames: list[tuple[float, list[Detection]]], config: PeopleConfig) -> list[Track]:
    """``frames``: (time, detections) in time order; the confirmed tracks seen at least
    ``min_detections`` times, numbered 1.. by when they start."""
    live: list[Track] = []
    done: list[Track] = []
    next_id = 1
    max_gap_s = coast_limit_s([t for t, _ in frames], config.max_gap_s)
    for t, found in frames:
        detections = [d for d in found if d.confidence >= config.match_confidence]
        still: list[Track] = []
        for tr in live:
            (still if t - tr.last_s <= max_gap_s else done).append(tr)
        live = still
        free = list(range(len(detections)))
        confirmed = [tr for tr in live if tr.confirmed]
        tentative = [tr for tr in live if not tr.confirmed]
        heads = []
        for i, j in _assign(confirmed, detections, free, t, config).items():
            _see(confirmed[i], t, detections[j])
            free.remove(j)
        for tr in confirmed:
            heads.append((np.asarray(tr.detections[-1].head_xy_m) if tr.last_s == t
                          else tr.predict(t, config.max_speed_m_s), tr.top_m()))  # fmt: skip
        free = [j for j in free if not _near(detections[j], heads, config)]
        for i, j in _assign(tentative, detections, free, t, config).items():
            _see(tentative[i], t, detections[j])
            free.remove(j)
        for tr in live:
            tr.age += 1
            if tr.last_s != t:
                tr.missed_s.append(t)
            if not tr.confirmed and len(tr.times_s) >= config.confirm_seen:
                tr.confirmed = True
        # a tentative track that can no longer be seen confirm_seen times in its first
        # confirm_timestamps ends here, unreported
        live = [tr for tr in live if tr.confirmed or _can_confirm(tr, config)]
        for j in free:
            if detections[j].confidence >= START_CONFIDENCE:
                live.append(Track(next_id, [t], [detections[j]]))
                next_id += 1
    # a track whose head sits, most of its life, among the room's background cubes is equipment
    # the background learned in part, not a person
    confirmed = sorted(
        (tr for tr in done + live if tr.confirmed and not _equipment(tr, config)),
        key=lambda tr: (tr.times_s[0], tr.id),
    )
    kept = [
        tr
        for tr in merge_duplicates(_linked(confirmed, config), config)
        if len(tr.times_s) >= config.min_detections
        and np.mean([d.confidence for d in tr.detections]) >= config.min_track_confidence
        and not _at_height_edge(tr, config)
    ]
    times_s = [t for t, _ in frames]
    for tr in kept:
        tr.missed_s = _unseen_s(tr, times_s)
    if config.fill_m > 0:
        _fill_misses(kept, frames, config)
    for k, tr in enumerate(kept, start=1):
        tr.id = k
    return kept


def _unseen_s(track: Track, times_s: list[float]) -> list[float]:
    """The timestamps between the track's first and last sighting at which it was not seen:
    those it coasted through and, where the linking joined two tracks, all of the time between
    them (the track's gaps)."""
    seen = {round(t, 6) for t in track.times_s}
    first, last = track.times_s[0], track.last_s
    return [t for t in times_s if first < t < last and round(t, 6) not in seen]


def _fill_misses(tracks: list[Track], frames: list[tuple[float, list[Detection]]],
                 config: PeopleConfig) -> None:  # fmt: skip
    """A track missed at a timestamp between two at which it was seen (at most
    ``fill_span_s`` apart: a moment it coasted through, or the time between two tracks the
    linking joined) takes a head found there that no track took, however doubtful, within
    ``fill_m`` of the line between them and within ``height_gate_m`` of their heads' height (the
    tracker's own gate): the recording is whole, so where the person was before and after says
    which head is theirs. The timestamps are taken
    in time order, so each head taken is where the line to the next starts."""
    used = {id(d) for tr in tracks for d in tr.detections}
    found = {round(t, 6): dets for t, dets in frames}
    height_m = config.height_gate_m
    for tr in tracks:
        times = list(tr.times_s)
        for t in sorted(set(tr.missed_s)):
            k = int(np.searchsorted(times, t))
            if not 0 < k < len(times) or times[k] - times[k - 1] > config.fill_span_s + 1e-6:
                continue
            a, b = tr.detections[k - 1], tr.detections[k]
            w = (t - times[k - 1]) / (times[k] - times[k - 1])
            where = (1 - w) * np.asarray(a.head_xy_m) + w * np.asarray(b.head_xy_m)
            top = 0.5 * (a.top_m + b.top_m)
            best, best_d = None, config.fill_m
            for d in found.get(round(t, 6), []):
                dist = float(np.hypot(*(np.asarray(d.head_xy_m) - where)))
                if id(d) not in used and dist <= best_d and abs(d.top_m - top) <= height_m:
                    best, best_d = d, dist
            if best is None:
                continue
            used.add(id(best))
            times.insert(k, t)
            tr.detections.insert(k, best)
            tr.missed_s = [m for m in tr.missed_s if abs(m - t) > 1e-6]
        tr.times_s = times


def _equipment(track: Track, config: PeopleConfig) -> bool:
    """A track that stays in one place (90 % of its heads within ``static_radius_m`` of their
    median) with its head among the room's background cubes most of the time
    (``static_share_max``), or one with many of them round its head wherever it goes
    (``static_share_moving``: stereo noise on a boom or a lamp hops about)."""
    xy = track.xy()
    spread = np.percentile(np.hypot(*(xy - np.median(xy, axis=0)).T), 90)
    share = np.median([d.static_share for d in track.detections])
    if config.static_share_moving > 0 and share > config.static_share_moving:
        return True
    return bool(spread <= config.static_radius_m and share > config.static_share_max)


def _at_height_edge(track: Track, config: PeopleConfig) -> bool:
    """A track whose head over its whole life (the median of its tops) sits within
    ``edge_head_m`` of the lowest or the highest head top the detector allows: something found
    at an end of the heads' height range for as long as it lasts, not a person (a standing
    adult's head top is well inside it over a track's life)."""
    if config.edge_head_m <= 0:
        return False
    height = track.height_m()
    return not (
        config.head_top_min_m + config.edge_head_m
        <= height
        <= config.head_top_max_m - config.edge_head_m
    )


def _can_confirm(track: Track, config: PeopleConfig) -> bool:
    left = config.confirm_timestamps - track.age
    return len(track.times_s) + left >= config.confirm_seen


def _see(track: Track, t: float, detection: Detection) -> None:
    track.times_s.append(t)
    track.detections.append(detection)


def _near(detection: Detection, heads: list[tuple[np.ndarray, float]], c: PeopleConfig) -> bool:
    """Whether ``detection`` is within ``duplicate_m`` of one of ``heads`` ((where, usual top))
    and not higher than that head's top by more than ``height_gate_m``: a shoulder or a second
    peak of a head is not above it; a taller person's head beside a shorter one is."""
    xy = np.asarray(detection.head_xy_m)
    return any(
        float(np.hypot(*(xy - h))) < c.duplicate_m and detection.top_m <= top + c.height_gate_m
        for h, top in heads
    )


def _linked(tracks: list[Track], config: PeopleConfig) -> list[Track]:
    """Tracks joined where one ends and another starts within ``stitch_gap_s`` after, where the
    gate reaches from where the first was last seen, the two of one height over their whole
    lives (a person missed for a while, not a new person): the pairs of least total cost over the
    whole case (``linear_sum_assignment``: each track has at most one successor and one
    predecessor), the time between becoming a gap. The recording is whole before tracking, so
    the linking looks at every track's end and start at once, not only the ones before it."""
    n = len(tracks)
    cost = np.full((n, n), NO_MATCH)
    for a, prev in enumerate(tracks):
        for b, tr in enumerate(tracks):
            gap = tr.times_s[0] - prev.last_s
            if not 0 < gap <= config.stitch_gap_s:
                continue
            d = float(np.hypot(*(tr.xy()[0] - prev.predict(tr.times_s[0], config.max_speed_m_s))))
            rise = abs(tr.height_m() - prev.height_m())
            if d <= config.gate_m + config.link_speed_m_s * gap and rise <= config.height_gate_m:
                cost[a, b] = d + config.height_weight * rise
    successor: dict[int, int] = {}
    if n:
        rows, cols = linear_sum_assignment(cost)
        successor = {
            int(a): int(b) for a, b in zip(rows, cols, strict=True) if cost[a, b] < NO_MATCH
        }
    has_prev = set(successor.values())
    out: list[Track] = []
    for a in range(n):
        if a in has_prev:
            continue
        head = tracks[a]
        while a in successor:
            a = successor[a]
            tr = tracks[a]
            head.missed_s.append(0.5 * (head.last_s + tr.times_s[0]))  # the gap between them
            head.times_s += tr.times_s
            head.detections += tr.detections
            head.missed_s += tr.missed_s
        out.append(head)
    return sorted(out, key=lambda tr: (tr.times_s[0], tr.id))
