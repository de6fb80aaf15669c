"""What each worker process of ``calibration.detect.extract`` does: a camera's background (the
median of its frames spread over the session), and for a chunk of sets, detect, label and bring
every camera's observation to its set's time (the module docstring of ``extract`` says why and
how well). Jobs are plain tuples, so they pickle to the processes; each process receives the
backgrounds once, through ``set_backgrounds``.

A frame whose image no longer matches its recorded checksum is skipped: left out of the
background and counted as a rejection with the reason ``DAMAGED`` (the wand is seen in many other
frames, so calibration goes on without it).
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detect.background import temporal_median
from calibration.detect.config import DetectorConfig
from calibration.detect.detector import SphereDetector
from calibration.detect.label import label_stereo, label_wand, refit_without_rod
from calibration.errors import ExtractionError
from calibration.observations import SIDES
from protocol.formats.wand import WandSpec
from protocol.formats.zed_conf import ConfFormatError, StereoCalibration, ZedFactoryCalibration
from protocol.images import EncodeError, decode_image
from protocol.session import CameraInfo, ImageChecksumError, SessionReader

ALIGN_EXACT_NS = 200_000  # closer than this to the set's time: use the frame as it is
DAMAGED = "damaged image (checksum mismatch)"  # the rejection reason of a skipped frame

_BACKGROUNDS: dict[tuple[int, str], np.ndarray] = {}  # a worker's copy, set once per process


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


def set_backgrounds(backgrounds: dict[tuple[int, str], np.ndarray]) -> None:
    """This process's backgrounds, per (camera serial, side)."""
    _BACKGROUNDS.clear()
    _BACKGROUNDS.update(backgrounds)


def background_work(args: tuple) -> tuple[int, np.ndarray, np.ndarray]:
    """One camera's two backgrounds: the median of its frames at ``rows`` (a worker process)."""
    path, identity, serial, rows = args
    cv2.setNumThreads(1)
    with SessionReader(path, identity=identity) as reader:
        cam = reader.info.camera(serial)
        frames: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
        for r in rows:
            try:
                buffers = reader.frame_bytes(serial, int(r))
            except ImageChecksumError:
                continue  # a median over the other frames: one fewer changes little
            for side_frames, buf in zip(frames, buffers, strict=True):
                side_frames.append(_decode(buf, cam))
    return serial, temporal_median(frames[0]), temporal_median(frames[1])


def work(args: tuple) -> tuple[np.ndarray, dict[str, dict[str, int]], int]:
    """Detect, label and time-align in a chunk of sets (runs in a worker process); the points
    (K, 2C, 3, 2), the rejections per camera and reason, and the number of frames decoded."""
    path, identity, set_rows, wand_mm, detector_cfg = args
    wand = WandSpec(sphere_diameter_mm=wand_mm[0], sphere_positions_mm=tuple(wand_mm[1]))
    cv2.setNumThreads(1)
    with SessionReader(path, identity=identity) as reader:
        chunk = _Chunk(reader, set_rows, wand, detector_cfg)
        points = np.full((len(set_rows), 2 * len(chunk.serials), 3, 2), np.nan)
        rejected: dict[str, dict[str, int]] = {}
        for i, k in enumerate(set_rows):
            t_ref = int(chunk.sets.set_unix_ns[k])
            for c, serial in enumerate(chunk.serials):
                row = int(chunk.sets.members[k, c])
                if row < 0:
                    continue
                at_set, reason = chunk.at_set_time(serial, row, t_ref)
                if at_set is None:
                    per = rejected.setdefault(f"SN{serial}", {})
                    per[reason] = per.get(reason, 0) + 1
                    continue
                points[i, 2 * c : 2 * c + 2] = at_set
    return points, rejected, len(chunk.cache)


def _decode(buf: bytes, cam: CameraInfo) -> np.ndarray:
    """One stored image, in whichever encoding its camera recorded, as BGR."""
    try:
        return decode_image(buf, cam.encoding, cam.width, cam.height)
    except EncodeError as exc:
        raise ExtractionError(
            f"camera SN{cam.camera_serial}: a stored frame cannot be decoded: {exc}; "
            "check the file with 'egosurg session verify'"
        ) from exc


class _Chunk:
    """A chunk's view of the session: a detector per sensor, each camera's frame times and
    period, the frames the chunk decodes anyway (each other's neighbours for the time
    alignment), and the labelled frames decoded so far."""

    def __init__(
        self,
        reader: SessionReader,
        set_rows: np.ndarray,
        wand: WandSpec,
        detector_cfg: DetectorConfig,
    ) -> None:
        self.reader, self.wand = reader, wand
        self.stereo = session_stereo(reader)
        self.serials = reader.info.camera_serials
        self.sets = reader.sets()
        self.stamps = {s: reader.frame_table(s)["capture_unix_ns"] for s in self.serials}
        self.period = {
            s: float(np.median(np.diff(v))) if len(v) > 1 else 1e9 for s, v in self.stamps.items()
        }
        self.detectors = {}
        for serial in self.serials:
            for side in SIDES:
                intr = self.stereo[serial].left if side == "left" else self.stereo[serial].right
                det = SphereDetector(intr, wand.radius_m, detector_cfg)
                det.set_background(_BACKGROUNDS[(serial, side)])
                self.detectors[(serial, side)] = det
        self.planned = {
            serial: {int(r) for r in self.sets.members[set_rows, c] if r >= 0}
            for c, serial in enumerate(self.serials)
        }
        self.cache: dict[tuple[int, int], tuple[np.ndarray | None, str]] = {}

    def observe(self, serial: int, row: int) -> tuple[np.ndarray | None, str]:
        """(2, 3, 2) left/right labelled centres of one frame, or None and the reason."""
        key = (serial, row)
        if key not in self.cache:
            try:
                left_buf, right_buf = self.reader.frame_bytes(serial, row)
            except ImageChecksumError:
                self.cache[key] = (None, DAMAGED)
                return self.cache[key]
            cam = self.reader.info.camera(serial)
            labels = []
            for side, buf in zip(SIDES, (left_buf, right_buf), strict=True):
                image = _decode(buf, cam)
                det = self.detectors[(serial, side)]
                label = label_wand(det.detect(image), self.wand)
                labels.append(refit_without_rod(det, image, label))
            res = label_stereo(labels[0], labels[1], self.stereo[serial], self.wand)
            if res.ok and res.left_px is not None and res.right_px is not None:
                self.cache[key] = (np.stack([res.left_px, res.right_px]), "")
            else:
                self.cache[key] = (None, res.reason or "rejected")
        return self.cache[key]

    def at_set_time(self, serial: int, row: int, t_ref: int) -> tuple[np.ndarray | None, str]:
        """The frame's centres brought to the set's time ``t_ref``, or None and the reason.

        Free-running cameras expose up to half a frame apart; bring every camera's observation
        to the set's reference time along its own neighbouring frame, so a moving wand is seen
        at one instant by all cameras."""
        here, reason = self.observe(serial, row)
        if here is None:
            return None, reason
        stamps = self.stamps[serial]
        t_here = int(stamps[row])
        if abs(t_ref - t_here) < ALIGN_EXACT_NS:
            return here, ""
        quadratic = self._quadratic(serial, row, t_ref)
        if quadratic is not None:
            return quadratic, ""
        step = 1 if t_ref > t_here else -1
        # interpolate with the frame on the far side of the set's time; where only the
        # frame on the near side is decoded anyway (the end of a run), extrapolate
        neighbours = [row + step, row - step]
        if row + step not in self.planned[serial] and row - step in self.planned[serial]:
            neighbours.reverse()
        why = "no neighbouring frame to align in time"
        for other in neighbours:
            if not 0 <= other < len(stamps) or (
                abs(int(stamps[other]) - t_here) > 1.5 * self.period[serial]
            ):  # the neighbour was dropped: nothing to align with
                continue
            there, reason = self.observe(serial, other)
            if there is None:
                why = f"neighbour frame: {reason}"
                continue
            w = (t_ref - t_here) / (int(stamps[other]) - t_here)
            return here + w * (there - here), ""
        return None, why

    def _quadratic(self, serial: int, row: int, t_ref: int) -> np.ndarray | None:
        """The centres at ``t_ref`` on the parabola through the frames before, at and after
        ``row``, when this chunk decodes all three anyway. A wand being picked up or swung
        round accelerates hard: at 15 fps a straight line between two frames misses its
        path by 0.2-0.6 px, the parabola by a tenth of that."""
        rows = (row - 1, row, row + 1)
        if not all(r in self.planned[serial] for r in rows):
            return None
        t = [int(self.stamps[serial][r]) for r in rows]
        if t[2] - t[0] > 2.5 * self.period[serial]:  # a dropped frame in between
            return None
        seen = [p for p in (self.observe(serial, r)[0] for r in rows) if p is not None]
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
