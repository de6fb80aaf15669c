"""``egosurg people``'s work: the background, then each timestamp's heads, the tracks, the poses.

Short sources (at most ``CACHE_FRAMES`` timestamps) are read once and kept; longer ones are read
twice: an even sample of ``BACKGROUND_SAMPLE`` timestamps to learn the room, then every
timestamp to find its people (a case's points are cheap to read again; a session's stereo is the
cost, see EVALUATION.md).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from reconstructor.people.background import Background
from reconstructor.people.config import PeopleConfig
from reconstructor.people.detect import Detection, detect, make_frame
from reconstructor.people.heightmap import Grid
from reconstructor.people.pose import HeadPose, group_sides, head_poses, ospace_points
from reconstructor.people.sources import PeopleInputError, Source
from reconstructor.people.track import Track, track_people

log = logging.getLogger(__name__)

CACHE_FRAMES = 80
BACKGROUND_SAMPLE = 60

Progress = Callable[[str, int, int], None]


@dataclass
class People:
    tracks: list[Track]
    poses: dict[int, list[HeadPose]]
    times_s: tuple[float, ...]
    background_from: str
    seconds: dict[str, float] = field(default_factory=dict)  # read, background, detect, track


def _grid(source: Source, config: PeopleConfig) -> Grid:
    x0, y0, x1, y1 = source.room_xy_m
    return Grid.covering(np.array([x0, y0]), np.array([x1, y1]), config.cell_m)


def find_people(
    source: Source,
    config: PeopleConfig,
    *,
    background: Source | None = None,
    progress: Progress | None = None,
) -> People:
    grid = _grid(source, config)
    seconds = {"read": 0.0, "background": 0.0, "detect": 0.0, "track": 0.0}
    n = len(source.times_s)
    cache: dict[int, np.ndarray] = {}

    def read(k: int) -> np.ndarray:
        if k in cache:
            return cache[k]
        t0 = time.perf_counter()
        points = source.points(k)
        seconds["read"] += time.perf_counter() - t0
        if n <= CACHE_FRAMES:
            cache[k] = points
        return points

    learned = Background.empty(grid)
    origin = []
    if background is not None:
        # the empty room is the better reference: someone who stands still through the whole
        # recording would be learned as part of the room
        clouds = [background.points(k) for k in range(len(background.times_s))]
        learned = Background.learn(grid, clouds, 1 / 3)
        origin.append(f"the empty room ({background.path}, {len(clouds)} timestamps)")
    elif n >= config.background_min_frames:
        sample = np.unique(np.linspace(0, n - 1, min(n, BACKGROUND_SAMPLE)).round().astype(int))
        clouds = []
        for i, k in enumerate(sample):
            clouds.append(read(int(k)))
            if progress:
                progress("background", i + 1, len(sample))
        t0 = time.perf_counter()
        learned = Background.learn(grid, clouds, config.background_share)
        seconds["background"] += time.perf_counter() - t0
        origin.append(f"the room over {len(sample)} of its timestamps")
        del clouds
    if not origin:
        raise PeopleInputError(
            f"{source.path} has {n} timestamp(s), too few to tell the room from its people "
            f"(at least {config.background_min_frames}): give a recording of the empty room "
            "with --background EMPTY.h5 (or its case), or more timestamps"
        )
    frames: list[tuple[float, list[Detection]]] = []
    for k, t in enumerate(source.times_s):
        points = read(k)
        t0 = time.perf_counter()
        frames.append((t, detect(make_frame(points, grid, learned, config), config)))
        seconds["detect"] += time.perf_counter() - t0
        if progress:
            progress("people", k + 1, n)
    t0 = time.perf_counter()
    tracks, poses = people_from_detections(frames, config)
    seconds["track"] = time.perf_counter() - t0
    return People(tracks, poses, source.times_s, " and ".join(origin), seconds)


def people_from_detections(
    frames: list[tuple[float, list[Detection]]], config: PeopleConfig
) -> tuple[list[Track], dict[int, list[HeadPose]]]:
    """Each timestamp's heads (time order) joined into tracks, and each track's head poses."""
    tracks = track_people(frames, config)
    heads: dict[float, list[tuple[float, float]]] = {}
    for tr in tracks:
        for t, d in zip(tr.times_s, tr.detections, strict=True):
            heads.setdefault(round(t, 6), []).append(d.head_xy_m)
    heads_at = {t: np.array(xy) for t, xy in heads.items()}
    shared = ospace_points(tracks, config)
    return tracks, {
        tr.id: head_poses(tr, config, group_sides(tr, heads_at, config), shared[tr.id])
        for tr in tracks
    }
