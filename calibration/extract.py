"""From a recorded wand session to ``WandObservations``: decode, detect, label, per set.

Steps:
1. read each camera's factory file from the session (intrinsics and the ZED's own stereo pose);
2. fit a background per sensor, the temporal median of frames spread over the session (the
   wand moves, the room mostly does not; ``calibration.background``);
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

import cv2
import numpy as np

from calibration.background import temporal_median
from calibration.detect import DetectorConfig, SphereDetector
from calibration.label import label_stereo, label_wand, refit_without_rod
from calibration.observations import SIDES, SensorKey, WandObservations
from protocol.errors import UserError
from protocol.formats.wand import WandSpec
from protocol.formats.zed_conf import ConfFormatError, StereoCalibration, ZedFactoryCalibration
from protocol.images import EncodeError, decode_image
from protocol.session import CameraInfo, SessionReader

log = logging.getLogger(__name__)


class ExtractionError(UserError, ValueError):
    pass


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


def session_stereo(reader: SessionReader) -> dict[int, StereoCalibration]:
    """Each camera's factory stereo calibration, at the resolution it recorded."""
    out = {}
    for cam in reader.info.cameras:
        if not cam.factory_conf_text.strip():
            raise ExtractionError(
                f"camera SN{cam.camera_serial} has no factory calibration in {reader.path}: its "
                "agent could not read SN<serial>.conf. Copy the file into the ZED settings folder "
                "on that node (/usr/local/zed/settings/) and record the wand session again"
            )
        try:
            factory = ZedFactoryCalibration.parse(
                cam.factory_conf_text,
                serial=cam.camera_serial,
                source=f"{reader.path} camera SN{cam.camera_serial} factory file",
            )
        except ConfFormatError as exc:
            raise ExtractionError(
                f"{exc}; record the wand session again with a good file"
            ) from None
        out[cam.camera_serial] = factory.stereo(cam.resolution)
    return out


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


def _decode(buf: bytes, cam: CameraInfo) -> np.ndarray:
    """One stored image, in whichever encoding its camera recorded, as BGR."""
    try:
        return decode_image(buf, cam.encoding, cam.width, cam.height)
    except EncodeError as exc:
        raise ExtractionError(
            f"camera SN{cam.camera_serial}: a stored frame cannot be decoded: {exc}; "
            "check the file with 'egosurg session verify'"
        ) from exc


_BACKGROUNDS: dict[tuple[int, str], np.ndarray] = {}  # a worker's copy, set once per process


def _set_backgrounds(backgrounds: dict[tuple[int, str], np.ndarray]) -> None:
    _BACKGROUNDS.clear()
    _BACKGROUNDS.update(backgrounds)


def _background_work(args: tuple) -> tuple[int, np.ndarray, np.ndarray]:
    """One camera's two backgrounds: the median of its frames at ``rows`` (a worker process)."""
    path, serial, rows = args
    cv2.setNumThreads(1)
    with SessionReader(path) as reader:
        cam = reader.info.camera(serial)
        frames: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
        for r in rows:
            for side_frames, buf in zip(frames, reader.frame_bytes(serial, int(r)), strict=True):
                side_frames.append(_decode(buf, cam))
    return serial, temporal_median(frames[0]), temporal_median(frames[1])


def _work(args: tuple) -> tuple[np.ndarray, dict[str, dict[str, int]], int]:
    """Detect, label and time-align in a chunk of sets (runs in a worker process); the points,
    the rejections and the number of frames decoded."""
    path, set_rows, wand_mm, detector_cfg = args
    wand = WandSpec(sphere_diameter_mm=wand_mm[0], sphere_positions_mm=tuple(wand_mm[1]))
    cv2.setNumThreads(1)
    with SessionReader(path) as reader:
        stereo = session_stereo(reader)
        serials = reader.info.camera_serials
        sets = reader.sets()
        stamps = {s: reader.frame_table(s)["capture_unix_ns"] for s in serials}
        period = {s: float(np.median(np.diff(v))) if len(v) > 1 else 1e9 for s, v in stamps.items()}
        detectors = {}
        for serial in serials:
            for side in SIDES:
                intr = stereo[serial].left if side == "left" else stereo[serial].right
                det = SphereDetector(intr, wand.radius_m, detector_cfg)
                det.set_background(_BACKGROUNDS[(serial, side)])
                detectors[(serial, side)] = det
        # the frames this chunk decodes anyway: each other's neighbours for the time alignment
        planned = {
            serial: {int(r) for r in sets.members[set_rows, c] if r >= 0}
            for c, serial in enumerate(serials)
        }
        cache: dict[tuple[int, int], tuple[np.ndarray | None, str]] = {}

        def observe(serial: int, row: int) -> tuple[np.ndarray | None, str]:
            """(2, 3, 2) left/right labelled centres of one frame, or None and the reason."""
            key = (serial, row)
            if key not in cache:
                left_buf, right_buf = reader.frame_bytes(serial, row)
                cam = reader.info.camera(serial)
                labels = []
                for side, buf in zip(SIDES, (left_buf, right_buf), strict=True):
                    image = _decode(buf, cam)
                    det = detectors[(serial, side)]
                    label = label_wand(det.detect(image), wand)
                    labels.append(refit_without_rod(det, image, label))
                res = label_stereo(labels[0], labels[1], stereo[serial], wand)
                if res.ok and res.left_px is not None and res.right_px is not None:
                    cache[key] = (np.stack([res.left_px, res.right_px]), "")
                else:
                    cache[key] = (None, res.reason or "rejected")
            return cache[key]

        def _quadratic(serial: int, row: int, t_ref: int) -> np.ndarray | None:
            """The centres at ``t_ref`` on the parabola through the frames before, at and after
            ``row``, when this chunk decodes all three anyway. A wand being picked up or swung
            round accelerates hard: at 15 fps a straight line between two frames misses its
            path by 0.2-0.6 px, the parabola by a tenth of that."""
            rows = (row - 1, row, row + 1)
            if not all(r in planned[serial] for r in rows):
                return None
            t = [int(stamps[serial][r]) for r in rows]
            if t[2] - t[0] > 2.5 * period[serial]:  # a dropped frame in between
                return None
            seen = [p for p in (observe(serial, r)[0] for r in rows) if p is not None]
            if len(seen) < 3:
                return None
            x = [(v - t[1]) / 1e9 for v in t]
            u = (t_ref - t[1]) / 1e9
            weights = [
                (u - x[1]) * (u - x[2]) / ((x[0] - x[1]) * (x[0] - x[2])),
                (u - x[0]) * (u - x[2]) / ((x[1] - x[0]) * (x[1] - x[2])),
                (u - x[0]) * (u - x[1]) / ((x[2] - x[0]) * (x[2] - x[1])),
            ]
            return weights[0] * seen[0] + weights[1] * seen[1] + weights[2] * seen[2]

        points = np.full((len(set_rows), 2 * len(serials), 3, 2), np.nan)
        rejected: dict[str, dict[str, int]] = {}

        def reject(serial: int, reason: str) -> None:
            per = rejected.setdefault(f"SN{serial}", {})
            per[reason] = per.get(reason, 0) + 1

        for i, k in enumerate(set_rows):
            t_ref = int(sets.set_unix_ns[k])
            for c, serial in enumerate(serials):
                row = int(sets.members[k, c])
                if row < 0:
                    continue
                here, reason = observe(serial, row)
                if here is None:
                    reject(serial, reason)
                    continue
                # Free-running cameras expose up to half a frame apart; bring every camera's
                # observation to the set's reference time along its own neighbouring frame, so
                # a moving wand is seen at one instant by all cameras.
                t_here = int(stamps[serial][row])
                if abs(t_ref - t_here) < ALIGN_EXACT_NS:
                    points[i, 2 * c : 2 * c + 2] = here
                    continue
                quadratic = _quadratic(serial, row, t_ref)
                if quadratic is not None:
                    points[i, 2 * c : 2 * c + 2] = quadratic
                    continue
                step = 1 if t_ref > t_here else -1
                # interpolate with the frame on the far side of the set's time; where only the
                # frame on the near side is decoded anyway (the end of a run), extrapolate
                neighbours = [row + step, row - step]
                if row + step not in planned[serial] and row - step in planned[serial]:
                    neighbours.reverse()
                aligned, why = None, "no neighbouring frame to align in time"
                for other in neighbours:
                    if not 0 <= other < len(stamps[serial]) or (
                        abs(int(stamps[serial][other]) - t_here) > 1.5 * period[serial]
                    ):  # the neighbour was dropped: nothing to align with
                        continue
                    there, reason = observe(serial, other)
                    if there is None:
                        why = f"neighbour frame: {reason}"
                        continue
                    w = (t_ref - t_here) / (int(stamps[serial][other]) - t_here)
                    aligned = here + w * (there - here)
                    break
                if aligned is None:
                    reject(serial, why)
                    continue
                points[i, 2 * c : 2 * c + 2] = aligned
    return points, rejected, len(cache)


ALIGN_EXACT_NS = 200_000  # closer than this to the set's time: use the frame as it is


def extract(
    session_path: str,
    wand: WandSpec,
    config: ExtractConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> WandObservations:
    cfg = config or ExtractConfig()
    with SessionReader(session_path) as reader:
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
    bg_jobs = [(session_path, serial, background_rows[serial]) for serial in serials]
    chunks = split_runs(chosen, max(1, workers * 4))
    jobs = [(session_path, chunk, wand_mm, cfg.detector) for chunk in chunks]
    backgrounds: dict[tuple[int, str], np.ndarray] = {}
    results = []
    if workers == 1:
        for serial, left, right in map(_background_work, bg_jobs):
            backgrounds[(serial, "left")], backgrounds[(serial, "right")] = left, right
        _set_backgrounds(backgrounds)
        for k, job in enumerate(jobs):
            results.append(_work(job))
            if progress:
                progress(k + 1, len(jobs))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for serial, left, right in pool.map(_background_work, bg_jobs):
                backgrounds[(serial, "left")], backgrounds[(serial, "right")] = left, right
        # a second pool, so each worker receives the backgrounds once rather than with every job
        with ProcessPoolExecutor(
            max_workers=workers, initializer=_set_backgrounds, initargs=(backgrounds,)
        ) as pool:
            for k, res in enumerate(pool.map(_work, jobs)):
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
