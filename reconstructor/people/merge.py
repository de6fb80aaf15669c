"""Two tracks that follow one person at the same time, joined into one.

The tracker starts a second track on a person when a head of theirs is found too far from
where their track expects it (a second peak of the head, a head found high or low for a
while): the two then live side by side, each seen while the other is missed, and whoever
reviews the recording sees one person as two, the view jumping between them. The recording
is whole before tracking, so the tracks can be compared over the whole of the time they
share: two whose heads stay within ``merge_m`` of each other through it (each head against
the other track's head at that timestamp, or where the other was between its sightings
just before and after), at the same height over their whole lives, are one person. The joined
track keeps, at each timestamp both saw, the surer head.
"""

from __future__ import annotations

from typing import Protocol, TypeVar

import numpy as np

from reconstructor.people.config import PeopleConfig
from reconstructor.people.detect import Detection


class _Track(Protocol):
    """What of ``reconstructor.people.track.Track`` the joining reads and sets (the tracker
    calls this module, so it names no type of the tracker's)."""

    id: int
    times_s: list[float]
    detections: list[Detection]
    missed_s: list[float]
    age: int

    @property
    def last_s(self) -> float: ...

    def height_m(self) -> float: ...


Track = TypeVar("Track", bound=_Track)

MIN_SHARED = 2  # heads in the shared time needed to call two tracks one person


def merge_duplicates(tracks: list[Track], config: PeopleConfig) -> list[Track]:
    """``tracks`` with each pair that follows one person at once joined, the closest pair
    first, until no pair is left (time order, the earlier track's id kept)."""
    if config.merge_m <= 0:
        return tracks
    out = list(tracks)
    while True:
        best: tuple[float, int, int] | None = None
        for i, a in enumerate(out):
            for j in range(i + 1, len(out)):
                d = _apart_m(a, out[j], config)
                if d is not None and (best is None or d < best[0]):
                    best = (d, i, j)
        if best is None:
            return sorted(out, key=lambda tr: (tr.times_s[0], tr.id))
        _, i, j = best
        joined = _join(out[i], out[j])
        out = [tr for k, tr in enumerate(out) if k not in (i, j)] + [joined]


def _where(track: _Track, t: float) -> np.ndarray | None:
    """The track's head at ``t``: seen there, or on the line between its sightings just before
    and after; None outside its life."""
    times = track.times_s
    k = int(np.searchsorted(times, t - 1e-6))
    if k < len(times) and abs(times[k] - t) < 1e-6:
        return np.asarray(track.detections[k].head_xy_m)
    if not 0 < k < len(times):
        return None
    a, b = track.detections[k - 1], track.detections[k]
    w = (t - times[k - 1]) / (times[k] - times[k - 1])
    return (1 - w) * np.asarray(a.head_xy_m) + w * np.asarray(b.head_xy_m)


def _apart_m(a: _Track, b: _Track, config: PeopleConfig) -> float | None:
    """The largest distance between the two tracks' heads over the time they share, where it
    is within ``merge_m`` and they are of one height; None for a pair that is two people (or
    shares too little time to tell)."""
    lo, hi = max(a.times_s[0], b.times_s[0]), min(a.last_s, b.last_s)
    if hi < lo or abs(a.height_m() - b.height_m()) > config.merge_height_m:
        return None
    dists = []
    for one, other in ((a, b), (b, a)):
        for t in one.times_s:
            if lo - 1e-6 <= t <= hi + 1e-6:
                there, here = _where(other, t), _where(one, t)
                if there is not None and here is not None:
                    dists.append(float(np.hypot(*(there - here))))
    if len(dists) < MIN_SHARED or max(dists) > config.merge_m:
        return None
    return max(dists)


def _join(a: Track, b: Track) -> Track:
    """The earlier of the two, now with both's heads, the surer one at a timestamp both saw."""
    heads: dict[float, tuple[float, Detection]] = {}
    for tr in (a, b):
        for t, d in zip(tr.times_s, tr.detections, strict=True):
            key = round(t, 6)
            if key not in heads or d.confidence > heads[key][1].confidence:
                heads[key] = (t, d)
    order = sorted(heads)
    seen = set(order)
    first, last = order[0], order[-1]
    missed = sorted({round(m, 6) for m in a.missed_s + b.missed_s if first < m < last} - seen)
    keep = a if (a.times_s[0], a.id) <= (b.times_s[0], b.id) else b
    keep.times_s = [heads[k][0] for k in order]
    keep.detections = [heads[k][1] for k in order]
    keep.missed_s = [float(m) for m in missed]
    keep.age = a.age + b.age
    return keep
