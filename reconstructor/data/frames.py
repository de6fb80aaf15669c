"""One timestamp of a session, read with its calibration: the images each sensor recorded there.

Reading a session (this module) is separate from turning it into training views (views.py).

``--at`` accepts:
- a time in seconds since the session started: ``12.5`` or ``12.5s``; the nearest set is used;
- a set index: ``set:120`` (``egosurg session info`` prints how many sets a session has).

A set in which some cameras are missing still reconstructs from the others; the missing cameras
are named in ``Timestamp.missing_serials`` and in the run's log. A camera whose image at the set
no longer matches its recorded checksum is left out the same way, with a warning naming camera,
row and side, and named in ``Timestamp.damaged_images`` (and the run's summary).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.camera import Camera, Intrinsics, Pose, Resolution
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.zed_conf import derive_intrinsics
from protocol.images import EncodeError, decode_image
from protocol.sealing import Identity
from protocol.sealing.derived import DerivedSeal
from protocol.session import CameraInfo, ImageChecksumError, SessionInfo, SessionReader
from protocol.session.derived import derived_seal
from reconstructor.errors import CalibrationMismatchError, ReconstructError, TimestampError

log = logging.getLogger(__name__)

SIDES = ("left", "right")


@dataclass(frozen=True)
class SensorFrame:
    """One sensor's image at the timestamp, with its calibrated camera at the session's size."""

    camera: Camera  # name "SN<serial>-<side>", intrinsics with distortion, world-to-camera pose
    camera_serial: int
    side: str
    image_rgb: np.ndarray  # (H, W, 3) uint8, as recorded (distorted)
    capture_unix_ns: int


@dataclass(frozen=True)
class Timestamp:
    session: Path
    set_index: int
    set_unix_ns: int
    t_s: float  # seconds since the session started
    frames: tuple[SensorFrame, ...]
    missing_serials: tuple[int, ...]
    resolution: Resolution
    # the images left out because they no longer match their checksums: "SN<serial> row <r> <side>"
    damaged_images: tuple[str, ...] = ()
    # a sealed session's: what is made from this timestamp (models, cached depth) is sealed
    # with it for the session's recipients, and opened with the identity it holds
    sealing: DerivedSeal | None = dataclasses.field(default=None, repr=False, compare=False)

    def sensor(self, camera_serial: int, side: str) -> SensorFrame:
        for f in self.frames:
            if f.camera_serial == camera_serial and f.side == side:
                return f
        raise KeyError(f"no frame of SN{camera_serial} {side} at set {self.set_index}")

    @property
    def camera_serials(self) -> tuple[int, ...]:
        return tuple(dict.fromkeys(f.camera_serial for f in self.frames))

    def stereo_pairs(self) -> list[tuple[SensorFrame, SensorFrame]]:
        return [(self.sensor(s, "left"), self.sensor(s, "right")) for s in self.camera_serials]


def resolve_at(at: str | float | int, set_unix_ns: np.ndarray, started_unix_ns: int) -> int:
    """The set index ``at`` names; see the module docstring for the accepted forms."""
    n = len(set_unix_ns)
    if n == 0:
        raise TimestampError("the session holds no synchronised sets; record a longer session")
    first_s = (int(set_unix_ns[0]) - started_unix_ns) / 1e9
    last_s = (int(set_unix_ns[-1]) - started_unix_ns) / 1e9
    valid = f"use a time from {first_s:.2f}s to {last_s:.2f}s, or set:0 to set:{n - 1}"
    text = str(at).strip().lower()
    if text.startswith("set:"):
        try:
            index = int(text[4:])
        except ValueError:
            raise TimestampError(f"--at {at!r} is not a set index; {valid}") from None
        if not 0 <= index < n:
            raise TimestampError(f"--at {at!r} is out of range: the session has {n} sets; {valid}")
        return index
    try:
        t_s = float(text[:-1] if text.endswith("s") else text)
    except ValueError:
        raise TimestampError(f"--at {at!r} is neither a time nor set:N; {valid}") from None
    # half a frame period of slack at each end, so "0" and the printed duration both work
    period_s = float(np.median(np.diff(set_unix_ns))) / 1e9 if n > 1 else 0.0
    if not (first_s - period_s <= t_s <= last_s + period_s) or not np.isfinite(t_s):
        raise TimestampError(f"--at {at!r} is out of range; {valid}")
    target_ns = started_unix_ns + round(t_s * 1e9)
    return int(np.argmin(np.abs(set_unix_ns.astype(np.int64) - target_ns)))


def session_intrinsics(
    calibration: RigCalibration, serial: int, side: str, resolution: Resolution
) -> Intrinsics:
    """The calibrated intrinsics at the resolution the session recorded."""
    intr = calibration.sensor(serial, side).intrinsics
    if calibration.resolution is resolution:
        return intr
    if calibration.resolution is Resolution.HD1200:
        return derive_intrinsics(intr, resolution)
    raise CalibrationMismatchError(
        f"the calibration is for {calibration.resolution.value} but the session recorded "
        f"{resolution.value}; calibrate at HD1200 (it derives every other mode) or at "
        f"{resolution.value}"
    )


def calibration_at(calibration: RigCalibration, resolution: Resolution) -> RigCalibration:
    """The same calibration with every sensor's intrinsics at ``resolution``."""
    if calibration.resolution is resolution:
        return calibration
    sensors = tuple(
        dataclasses.replace(
            s, intrinsics=session_intrinsics(calibration, s.camera_serial, s.side, resolution)
        )
        for s in calibration.sensors
    )
    return dataclasses.replace(calibration, sensors=sensors, resolution=resolution)


def check_calibration(info: SessionInfo, calibration: RigCalibration, source: str) -> None:
    """Every camera of the session must be in the calibration, with both sensors."""
    have = set(calibration.camera_serials)
    missing = [s for s in info.camera_serials if s not in have]
    if missing:
        names = ", ".join(f"SN{s}" for s in missing)
        known = ", ".join(f"SN{s}" for s in sorted(have))
        raise CalibrationMismatchError(
            f"{source} does not calibrate camera(s) {names} of {info.path} (it has {known}); "
            "calibrate this rig with 'egosurg calibrate' on a wand session recorded with it"
        )
    for serial in info.camera_serials:
        for side in SIDES:
            try:
                calibration.sensor(serial, side)
            except Exception as exc:
                raise CalibrationMismatchError(f"{source}: {exc}") from exc


def load_timestamp(
    session: Path | str,
    calibration: RigCalibration,
    at: str | float | int,
    *,
    calibration_source: str = "the calibration",
    identity: Identity | None = None,
) -> Timestamp:
    """Decode every sensor's image of the set ``at`` names; a camera whose image is damaged is
    left out with a warning (see the module docstring). A sealed session is opened with
    ``identity`` (``IdentityRequiredError``, naming its recipients, without one)."""
    path = Path(session)
    with SessionReader(path, identity=identity) as reader:
        reader.require_identity("every image")
        info = reader.info
        check_calibration(info, calibration, calibration_source)
        sets = reader.sets()
        index = resolve_at(at, sets.set_unix_ns, info.started_unix_ns)
        members = sets.members[index]
        frames: list[SensorFrame] = []
        missing: list[int] = []
        damaged: list[str] = []
        resolution = Resolution.parse(info.cameras[0].resolution)
        for column, serial in enumerate(info.camera_serials):
            row = int(members[column])
            if row < 0:
                missing.append(serial)
                continue
            cam_info = info.camera(serial)
            res = Resolution.parse(cam_info.resolution)
            if res is not resolution:
                raise ReconstructError(
                    f"{path}: cameras recorded different modes ({resolution.value} and "
                    f"{res.value} for SN{serial}); the reconstructor needs one mode"
                )
            try:
                frames += _camera_frames(reader, cam_info, row, calibration, res)
            except ImageChecksumError as exc:
                damaged.append(f"SN{serial} row {exc.row} {exc.side}")
                log.warning(
                    "set %d: SN%d row %d %s image does not match its recorded checksum; "
                    "reconstructing without SN%d ('egosurg session verify' lists the damage)",
                    index,
                    serial,
                    exc.row,
                    exc.side,
                    serial,
                )
        if not frames:
            raise ReconstructError(
                f"{path}: set {index} has no usable camera (missing or damaged); choose another "
                "--at ('egosurg session info' shows the sets)"
            )
        if missing:
            log.warning(
                "set %d is missing camera(s) %s: reconstructing from the other %d",
                index,
                ", ".join(f"SN{s}" for s in missing),
                len(frames) // 2,
            )
        set_ns = int(sets.set_unix_ns[index])
        return Timestamp(
            session=path,
            set_index=index,
            set_unix_ns=set_ns,
            t_s=(set_ns - info.started_unix_ns) / 1e9,
            frames=tuple(frames),
            missing_serials=tuple(missing),
            resolution=resolution,
            damaged_images=tuple(damaged),
            sealing=derived_seal(reader, identity),
        )


def _camera_frames(
    reader: SessionReader,
    cam_info: CameraInfo,
    row: int,
    calibration: RigCalibration,
    res: Resolution,
) -> list[SensorFrame]:
    """Both sensors' decoded images of one camera's frame ``row``; ``ImageChecksumError`` when
    either image is damaged (both are read before either is used)."""
    serial = cam_info.camera_serial
    stamp = int(reader.frame_table(serial)["capture_unix_ns"][row])
    buffers = reader.frame_bytes(serial, row)
    out = []
    for side, buf in zip(SIDES, buffers, strict=True):
        try:
            bgr = decode_image(buf, cam_info.encoding, cam_info.width, cam_info.height)
        except EncodeError as exc:
            raise ReconstructError(
                f"{reader.path}: SN{serial} {side} frame {row} cannot be decoded ({exc}); "
                "run 'egosurg session verify' on the file"
            ) from exc
        camera = Camera(
            name=f"SN{serial}-{side}",
            intrinsics=session_intrinsics(calibration, serial, side, res),
            pose=calibration.sensor(serial, side).pose,
        )
        out.append(
            SensorFrame(
                camera=camera,
                camera_serial=serial,
                side=side,
                image_rgb=np.ascontiguousarray(bgr[:, :, ::-1]),
                capture_unix_ns=stamp,
            )
        )
    return out


def right_from_left(left: Camera, right: Camera) -> Pose:
    """The stereo extrinsics ``x_right = R x_left + t`` from two calibrated world poses."""
    return right.pose.compose(left.pose.inverse())
