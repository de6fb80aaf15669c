"""From a recorded wand session to ``WandObservations``: decode, detect, label, per set.

Steps:
1. read each camera's factory file from the session (intrinsics and the ZED's own stereo pose);
2. fit a background per sensor from frames spread over the session (the wand moves, the room
   mostly does not);
3. for the chosen synchronised sets, detect the spheres in every sensor's image, label them from
   the wand's unequal spacing, and keep a camera's pair only if its own stereo triangulation gives
   the wand's geometry back; every rejection is counted with its reason.

Sets are taken by capture-time synchronisation (the session's set table, tolerance half a frame
period). Decoding an HD1200 JPEG costs about 10 ms, so long sessions are subsampled evenly to at
most ``max_sets`` sets (the first seconds, where the wand may lie on the floor, are always kept),
and the work is spread over processes.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.detect import DetectorConfig, SphereDetector
from calibration.label import label_stereo, label_wand, refit_without_rod
from calibration.observations import SIDES, SensorKey, WandObservations
from protocol.errors import UserError
from protocol.images import EncodeError, decode_image
from protocol.session import CameraInfo, SessionReader
from protocol.wand import WandSpec
from protocol.zed_conf import ConfFormatError, StereoCalibration, ZedFactoryCalibration

log = logging.getLogger(__name__)


class ExtractionError(UserError, ValueError):
    pass


@dataclass(frozen=True, kw_only=True)
class ExtractConfig:
    max_sets: int = 600
    keep_first_s: float = 3.0  # always keep every set of the first seconds (wand on the floor)
    background_frames: int = 15
    workers: int = 0  # 0: one per core, at most 2 on the reference workstation
    detector: DetectorConfig = field(default_factory=DetectorConfig)

    def __post_init__(self) -> None:
        if self.max_sets < 10:
            raise ExtractionError(f"max_sets={self.max_sets} is too small to calibrate from")


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
    n = len(set_unix_ns)
    if n <= config.max_sets:
        return np.arange(n)
    early = np.flatnonzero(set_unix_ns - set_unix_ns[0] <= config.keep_first_s * 1e9)
    rest = np.setdiff1d(np.arange(n), early)
    budget = max(config.max_sets - len(early), 1)
    pick = rest[np.linspace(0, len(rest) - 1, min(budget, len(rest))).round().astype(int)]
    return np.unique(np.concatenate([early, pick]))


def _decode(buf: bytes, cam: CameraInfo) -> np.ndarray:
    """One stored image, in whichever encoding its camera recorded, as BGR."""
    try:
        return decode_image(buf, cam.encoding, cam.width, cam.height)
    except EncodeError as exc:
        raise ExtractionError(
            f"camera SN{cam.camera_serial}: a stored frame cannot be decoded: {exc}; "
            "check the file with 'egosurg session verify'"
        ) from exc


def _work(args: tuple) -> tuple[np.ndarray, dict[str, dict[str, int]]]:
    """Detect, label and time-align in a chunk of sets (runs in a worker process)."""
    path, set_rows, wand_mm, detector_cfg, backgrounds = args
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
                # the median was taken in the parent; the median of copies of it is itself
                det.fit_background([backgrounds[(serial, side)]] * 3)
                detectors[(serial, side)] = det
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
                # observation to the set's reference time by interpolating along its own
                # neighbouring frame, so a moving wand is seen at one instant by all cameras.
                t_here = int(stamps[serial][row])
                if abs(t_ref - t_here) < ALIGN_EXACT_NS:
                    points[i, 2 * c : 2 * c + 2] = here
                    continue
                other = row + 1 if t_ref > t_here else row - 1
                if not 0 <= other < len(stamps[serial]) or (
                    abs(int(stamps[serial][other]) - t_here) > 1.5 * period[serial]
                ):  # the neighbour was dropped: nothing to interpolate with
                    reject(serial, "no neighbouring frame to align in time")
                    continue
                there, reason = observe(serial, other)
                if there is None:
                    reject(serial, f"neighbour frame: {reason}")
                    continue
                w = (t_ref - t_here) / (int(stamps[serial][other]) - t_here)
                points[i, 2 * c : 2 * c + 2] = here + w * (there - here)
    return points, rejected


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
        backgrounds = {}
        for serial in serials:
            n = reader.frame_count(serial)
            rows = np.linspace(0, n - 1, min(cfg.background_frames, n)).round().astype(int)
            for s, side in enumerate(SIDES):
                cam = reader.info.camera(serial)
                frames = [_decode(reader.frame_bytes(serial, int(r))[s], cam) for r in rows]
                backgrounds[(serial, side)] = np.median(np.stack(frames), axis=0).astype(np.uint8)
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
    chunks = [c for c in np.array_split(chosen, max(1, workers * 4)) if len(c)]
    wand_mm = (wand.sphere_diameter_mm, list(wand.sphere_positions_mm))
    jobs = [(session_path, chunk, wand_mm, cfg.detector, backgrounds) for chunk in chunks]
    results = []
    if workers == 1:
        for k, job in enumerate(jobs):
            results.append(_work(job))
            if progress:
                progress(k + 1, len(jobs))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for k, res in enumerate(pool.map(_work, jobs)):
                results.append(res)
                if progress:
                    progress(k + 1, len(jobs))
    points = np.concatenate([r[0] for r in results])
    rejected: dict[SensorKey, dict[str, int]] = {}
    for _, rej in results:
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
    )
    used = obs.frames_used()
    for key in obs.sensors:
        log.info("%s: wand found in %d of %d sets", key.name, used[key], frames_seen[key])
    return obs
