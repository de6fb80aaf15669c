"""From a recorded wand session to ``WandObservations``: decode, detect, label, per set.

Steps:
1. read each camera's factory file from the session (intrinsics and the ZED's own stereo pose);
2. fit a background per sensor, the temporal median of frames spread over the session (the
   wand moves, the room mostly does not; ``calibration.detect.background``);
3. for the chosen synchronised sets, detect the spheres in every sensor's image, label them from
   the wand's unequal spacing, and keep a camera's pair only if its own stereo triangulation gives
   the wand's geometry back; every rejection is counted with its reason.

Sets are taken by capture-time synchronisation (the session's set table, tolerance half a frame
period). Free-running cameras expose up to half a frame apart, so each camera's observation is
brought to its set's time along the camera's own neighbouring frames: on the parabola through
the frames before, at and after, where all three are read anyway; else on the line to the
frame across the set's time (or, at the end of a run, extrapolated by at most half a frame, see
below). On a 15 fps session of the simulator the parabola halves the calibration's position
error (1.9 -> 0.8 mm): the wand being picked up accelerates too hard for a straight line.

Cost: decoding an HD1200 JPEG takes about 18 ms, whatever else is done, and detection about as
much again; a 2-minute session at 30 fps holds 28 800 images. So long sessions are subsampled to
at most ``max_sets`` sets, evenly in time, in runs of ``run_length`` consecutive sets (the first
``keep_first_s`` seconds, where the wand may lie on the floor, are always kept whole). Within a
run the frames of one set are the time-alignment neighbours of the next, so a run of L sets costs
L decoded frames per camera rather than 2L: the run's first or last set is extrapolated from the
frame after or before it (by at most half a frame; at 30 fps that moves a sphere by 0.06 mm in
the median, against 0.04 mm for interpolation, on the simulator's wand). The work is spread over
processes.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from calibration.detect.config import DetectorConfig
from calibration.detect.worker import background_work, session_stereo, set_backgrounds, work
from calibration.errors import ExtractionError
from calibration.observations import SIDES, SensorKey, WandObservations
from protocol.formats.wand import WandSpec
from protocol.sealing import Identity
from protocol.session import SessionReader

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ExtractConfig:
    max_sets: int = 300  # 2 min at 30 fps: 47 s, 0.33 mm; 600 sets: 88 s, 0.25 mm (BENCHMARKS.md)
    run_length: int = 2  # consecutive sets taken together (see the module docstring)
    keep_first_s: float = 3.0  # always keep every set of the first seconds (wand on the floor)
    background_frames: int = 15
    workers: int = 0  # 0: one per core, at most 2 on the reference workstation
    detector: DetectorConfig = field(default_factory=DetectorConfig)

    def __post_init__(self) -> None:
        if self.max_sets < 10:
            raise ExtractionError(f"max_sets={self.max_sets} is too small to calibrate from")
        if not 1 <= self.run_length <= self.max_sets // 4:
            raise ExtractionError(
                f"run_length={self.run_length} must be between 1 and max_sets/4 "
                f"({self.max_sets // 4})"
            )
        if not 3 <= self.background_frames <= 63:
            raise ExtractionError(
                f"background_frames={self.background_frames} must be between 3 and 63"
            )


def choose_sets(set_unix_ns: np.ndarray, config: ExtractConfig) -> np.ndarray:
    """Rows of the set table to use: all of them, or ``max_sets`` of them: the first
    ``keep_first_s`` seconds whole, then runs of ``run_length`` consecutive sets spread evenly."""
    n = len(set_unix_ns)
    if n <= config.max_sets:
        return np.arange(n)
    early = np.flatnonzero(set_unix_ns - set_unix_ns[0] <= config.keep_first_s * 1e9)
    early = early[: config.max_sets // 2]
    first = int(early[-1]) + 1 if len(early) else 0
    length = config.run_length
    n_runs = max((config.max_sets - len(early)) // length, 1)
    last_start = max(n - length, first)
    starts = np.linspace(first, last_start, n_runs).round().astype(int)
    pick = (starts[:, None] + np.arange(length)[None, :]).ravel()
    return np.unique(np.concatenate([early, pick[pick < n]]))


def split_runs(chosen: np.ndarray, n_chunks: int) -> list[np.ndarray]:
    """``chosen`` (sorted rows) cut into about ``n_chunks`` pieces of similar size, never inside
    a run of consecutive rows shorter than a piece (its frames align each other in time)."""
    if len(chosen) == 0:
        return []
    breaks = np.flatnonzero(np.diff(chosen) != 1) + 1
    runs = np.split(chosen, breaks)
    target = max(1, math.ceil(len(chosen) / max(n_chunks, 1)))
    chunks: list[np.ndarray] = []
    current: list[np.ndarray] = []
    size = 0
    for run in runs:
        for piece in np.array_split(run, max(1, len(run) // target)):
            current.append(piece)
            size += len(piece)
            if size >= target:
                chunks.append(np.concatenate(current))
                current, size = [], 0
    if current:
        chunks.append(np.concatenate(current))
    return chunks


def extract(
    session_path: str,
    wand: WandSpec,
    config: ExtractConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
    identity: Identity | None = None,
) -> WandObservations:
    """The wand in the session's frames; a sealed session is opened with ``identity``."""
    cfg = config or ExtractConfig()
    with SessionReader(session_path, identity=identity) as reader:
        reader.require_identity("every image")  # said here once, not by each worker
        stereo = session_stereo(reader)
        serials = reader.info.camera_serials
        sets = reader.sets()
        if len(sets.set_unix_ns) == 0:
            raise ExtractionError(f"{session_path} holds no synchronised sets to calibrate from")
        chosen = choose_sets(sets.set_unix_ns, cfg)
        background_rows = {}
        for serial in serials:
            n = reader.frame_count(serial)
            rows = np.linspace(0, n - 1, min(cfg.background_frames, n)).round().astype(int)
            background_rows[serial] = np.unique(rows)
            if len(background_rows[serial]) < 3:
                raise ExtractionError(
                    f"camera SN{serial} recorded only {n} frames in {session_path}: too few to "
                    "calibrate from; record the wand for a minute or two"
                )
        frames_seen = {
            SensorKey(serial, side): int((sets.members[chosen, c] >= 0).sum())
            for c, serial in enumerate(serials)
            for side in SIDES
        }
        sizes = {
            SensorKey(cam.camera_serial, side): (cam.width, cam.height)
            for cam in reader.info.cameras
            for side in SIDES
        }
    workers = cfg.workers or min(2, os.cpu_count() or 1)
    wand_mm = (wand.sphere_diameter_mm, list(wand.sphere_positions_mm))
    bg_jobs = [(session_path, identity, serial, background_rows[serial]) for serial in serials]
    chunks = split_runs(chosen, max(1, workers * 4))
    jobs = [(session_path, identity, chunk, wand_mm, cfg.detector) for chunk in chunks]
    backgrounds: dict[tuple[int, str], np.ndarray] = {}
    results = []
    if workers == 1:
        for serial, left, right in map(background_work, bg_jobs):
            backgrounds[(serial, "left")], backgrounds[(serial, "right")] = left, right
        set_backgrounds(backgrounds)
        for k, job in enumerate(jobs):
            results.append(work(job))
            if progress:
                progress(k + 1, len(jobs))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for serial, left, right in pool.map(background_work, bg_jobs):
                backgrounds[(serial, "left")], backgrounds[(serial, "right")] = left, right
        # a second pool, so each worker receives the backgrounds once rather than with every job
        with ProcessPoolExecutor(
            max_workers=workers, initializer=set_backgrounds, initargs=(backgrounds,)
        ) as pool:
            for k, res in enumerate(pool.map(work, jobs)):
                results.append(res)
                if progress:
                    progress(k + 1, len(jobs))
    points = np.concatenate([r[0] for r in results])
    decoded = sum(r[2] for r in results)
    rejected: dict[SensorKey, dict[str, int]] = {}
    for _, rej, _ in results:
        for name, reasons in rej.items():
            serial = int(name[2:])
            for side in SIDES:
                per = rejected.setdefault(SensorKey(serial, side), {})
                for reason, count in reasons.items():
                    per[reason] = per.get(reason, 0) + count
    obs = WandObservations(
        wand=wand,
        camera_serials=tuple(serials),
        stereo=stereo,
        set_unix_ns=sets.set_unix_ns[chosen],
        points_px=points,
        rejected=rejected,
        frames_seen=frames_seen,
        image_size=sizes,
        frames_decoded=2 * decoded,
    )
    used = obs.frames_used()
    for key in obs.sensors:
        log.info("%s: wand found in %d of %d sets", key.name, used[key], frames_seen[key])
    log.info("%d sets from %d decoded images", len(chosen), 2 * decoded)
    return obs
