"""``replay``: render a camera path through a case's models over time into an MP4.

Each output frame at case time t renders the path's camera at t into the case's model at t (the
last done timestamp at or before t); a time code and the model's name are burned in. Without
``--from``/``--to`` it spans what both the case and the path cover: from the later of the first
model and the first keyframe to the earlier of the last model and the last keyframe (a path
that runs on past the case would show its last model frozen). A frame whose model is older
than the case's spacing (past a gap, or past the case's end when ``--to`` asks for it) is
marked ``STALE`` with the model's age, and counted in ``ReplayStats.stale_frames``. The
models come from :class:`ModelSource`, which reads ahead in a thread when ``preload`` is on.

A frame inside one of the path's gaps (an estimated role hidden from every camera there, or
between two of the tracks it joins: ``reconstructor/replay/names.py``) shows no view: nobody
knows where that eye was, and a view from the spline through the gap would look real. It is a
grey card that says ``NOT FOLLOWED`` with the gap's span, keeps the video's clock (the grid's
real cameras still show that instant), and is counted in ``ReplayStats.gap_frames``.

Each frame is for a team to read (``frame.py``, ``clock.py``): the time of day and the case's
id are burned in above the case time, and pixels no Gaussian covers show as a magenta hatch with
a legend ("no data"), not as black. With ``--pip`` the nearest real camera's frame is inset;
with ``--layout grid`` four of the rig's real cameras (the nearest the path) fill a 2 x 2 grid
beside the render, each a quarter of its size, at the set nearest the frame's time. An image
that no longer matches its recorded checksum is never shown: the inset or cell says "DAMAGED"
with its camera and row instead, the run logs a warning and ``ReplayStats.damaged_images``
lists it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from protocol.camera import Camera
from protocol.errors import UserError
from protocol.formats.rig_calibration import RigCalibration
from protocol.sealing import Identity
from reconstructor.case.index import Entry
from reconstructor.config import ReconstructConfig
from reconstructor.data.views import novel_view
from reconstructor.errors import CaseReplayError
from reconstructor.raster import RasterConfig
from reconstructor.raster.device import for_device
from reconstructor.replay.clock import CaseClock, pick_zone
from reconstructor.replay.frame import grid_layout, no_data_legend, show_no_data
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.observed_case import ReplayObserved
from reconstructor.replay.path import CameraPath
from reconstructor.replay.video import Mp4Writer, burn_text, paste_pip, timecode
from reconstructor.splats.gaussians import Gaussians
from reconstructor.splats.train import render

log = logging.getLogger(__name__)
LAYOUTS = ("render", "grid")  # the render alone (--pip: one inset), or beside 4 real cameras
GRID_CAMERAS = 4


@dataclass(frozen=True, kw_only=True)
class ReplayConfig:
    fps: float = 10.0
    size_px: tuple[int, int] = (960, 600)
    t_from_s: float | None = None  # default: the later of the path's and the case's starts
    t_to_s: float | None = None  # default: the earlier of the path's and the case's ends
    preload: bool = True
    near_m: float = 0.0  # 0: the model's near plane; 0.2 from a person's eye (EYE_NEAR_M)
    pip: bool = False
    allow_gaps: bool = False
    observed: bool = False  # also OUT.observed.mp4 and .csv (replay/observed_case.py)
    device: str = "cpu"  # "cuda": render on gsplat's CUDA rasterizer (docs/gpu.md)
    layout: str = "render"  # "grid": the render beside a 2 x 2 grid of real cameras (2W x H)
    timezone: str | None = None  # the time of day's zone (IANA name); None: the machine's

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"--layout {self.layout!r}: give one of {', '.join(LAYOUTS)}")
        if self.layout == "grid" and self.pip:
            raise ValueError("--pip and --layout grid both show the real cameras: give one")
        if not 0.1 <= self.fps <= 240:
            raise ValueError(f"fps {self.fps}: give 0.1 to 240 frames per second")
        if not (16 <= self.size_px[0] <= 8192 and 16 <= self.size_px[1] <= 8192):
            raise ValueError(f"size {self.size_px}: 16 to 8192 px a side")

    @property
    def video_size_px(self) -> tuple[int, int]:
        """The MP4's width and height: twice as wide with the grid beside the render."""
        w, h = self.size_px
        return (2 * w, h) if self.layout == "grid" else (w, h)


@dataclass(frozen=True)
class ReplayStats:
    frames: int
    models: int  # distinct models shown
    wall_s: float
    load_wait_s: float  # time blocked on reading models (what preloading hides)
    t_from_s: float
    t_to_s: float
    damaged_images: tuple[str, ...] = ()  # --pip frames not shown: "SN<serial> row <r> left"
    stale_frames: int = 0  # frames marked STALE: their model older than the case's spacing
    spacing_s: float = 0.0  # the case's interval between timestamps
    gap_frames: int = 0  # frames inside the path's gaps: a NOT FOLLOWED card, no view

    @property
    def fps(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0


def case_raster(folder: Path, near_m: float = 0.0, device: str = "cpu") -> RasterConfig:
    cfg = folder / "config.toml"
    raster = ReconstructConfig.read(cfg).raster if cfg.is_file() else RasterConfig()
    raster = for_device(raster, device)  # a GPU-made case replays on the CPU by default
    if near_m > raster.near_m:
        raster = dataclasses.replace(raster, near_m=near_m)
    return raster


def render_view(g: Gaussians, camera: Camera, raster: RasterConfig):
    """(uint8 RGB (H, W, 3), depth_m (H, W), alpha (H, W)) numpy arrays."""
    with torch.no_grad():
        out = render(g, novel_view(camera), raster, torch.zeros(3))
    rgb = (out.image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    return rgb, out.depth_m.numpy(), out.alpha.numpy()


def frame_times(path: CameraPath, models: CaseModels, config: ReplayConfig) -> np.ndarray:
    p0, p1 = path.span_s
    c0, c1 = models.span_s
    t0 = max(p0, c0) if config.t_from_s is None else config.t_from_s
    t1 = min(p1, c1) if config.t_to_s is None else config.t_to_s
    if t1 < t0:
        raise CaseReplayError(
            f"nothing to replay: trajectory {path.name!r} spans {p0:.3f}-{p1:.3f} s and the "
            f"case {c0:.3f}-{c1:.3f} s"
        )
    path.require_inside(t0, "replay start")
    path.require_inside(t1, "replay end")
    models.require_span(t0, t1, config.allow_gaps)
    n = int(np.floor((t1 - t0) * config.fps + 1e-6)) + 1
    return t0 + np.arange(n) / config.fps


class RealCameras:
    """The session's frame from the real camera nearest an eye, at the set nearest a time."""

    def __init__(
        self, models: CaseModels, identity: Identity | None = None, clock: CaseClock | None = None
    ) -> None:
        from protocol.images import decode_image
        from protocol.session import ImageChecksumError, SessionReader

        self._decode = decode_image
        self._damage_error = ImageChecksumError
        self.damaged: list[str] = []  # "SN<serial> row <r> left", in the order first met
        session = Path(models.index.session)
        cal = models.folder / "calibration.toml"
        if not session.is_file() or not cal.is_file():
            raise CaseReplayError(
                f"the real cameras (--pip, --layout grid) need the case's session ({session}) "
                f"and {cal}; put the session back at that path or replay without them"
            )
        self.sensors = [s for s in RigCalibration.read(cal).sensors if s.side == "left"]
        self.reader = SessionReader(session, identity=identity)
        try:
            self.reader.require_identity("the real cameras' frames (--pip, --layout grid)")
        except BaseException:
            self.reader.close()
            raise
        sets = self.reader.sets()
        self.set_t_s = (sets.set_unix_ns - self.reader.info.started_unix_ns) / 1e9
        self.members = sets.members
        self.clock = clock
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def nearest(self, eyes_m: np.ndarray, count: int) -> list:
        """The ``count`` left sensors nearest the mean of ``eyes_m`` ((N, 3)), nearest first."""
        centre = np.asarray(eyes_m, float).reshape(-1, 3).mean(axis=0)
        order = np.argsort([np.linalg.norm(s.pose.centre_m - centre) for s in self.sensors])
        return [self.sensors[int(k)] for k in order[:count]]

    def frame(self, eye_m: np.ndarray, t_s: float) -> tuple[np.ndarray, str] | None:
        """The nearest camera's frame at the set nearest ``t_s``; None when it has none there."""
        image, label = self.sensor_frame(self.nearest(eye_m, 1)[0], t_s)
        return None if image is None else (image, label)

    def sensor_frame(self, sensor, t_s: float) -> tuple[np.ndarray | None, str]:
        """(RGB image or None when the camera has no frame in that set, label) of ``sensor``'s
        left image at the set nearest ``t_s``."""
        k = int(np.argmin(np.abs(self.set_t_s - t_s)))
        col = self.reader.info.camera_serials.index(sensor.camera_serial)
        row = int(self.members[k, col])
        when = self.clock.time_of_day(self.set_t_s[k]) if self.clock is not None else ""
        label = f"{sensor.name} {when or timecode(self.set_t_s[k])}"
        if row < 0:
            return None, f"{sensor.name}: no frame in this set"
        key = (sensor.camera_serial, row)
        if key not in self._cache:
            info = self.reader.info.camera(sensor.camera_serial)
            try:
                left = self.reader.image_bytes(sensor.camera_serial, row, "left")
            except self._damage_error:
                return self._damaged(sensor.camera_serial, row, info.width, info.height)
            bgr = self._decode(left, info.encoding, info.width, info.height)
            if len(self._cache) >= 2 * GRID_CAMERAS:  # a set's worth and the next: small memory
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = np.ascontiguousarray(bgr[:, :, ::-1])
        return self._cache[key], label

    def _damaged(self, serial: int, row: int, width: int, height: int) -> tuple[np.ndarray, str]:
        """A dark inset that says the real frame is damaged, never the changed image."""
        name = f"SN{serial} row {row} left"
        if name not in self.damaged:
            self.damaged.append(name)
            log.warning("--pip: %s image does not match its recorded checksum; not shown", name)
        h = max(16, round(160 * height / max(width, 1)))
        return np.full((h, 160, 3), 40, np.uint8), f"DAMAGED SN{serial} row {row}"

    def close(self) -> None:
        self.reader.close()


STALE_SLACK_S = 1e-3  # timestamps' times are stored to the millisecond
GAP_GREY = 64  # a gap card's background: no render is this flat


def gap_card(size_px: tuple[int, int], lines: list[str], gap: tuple[float, float], who: str):
    """The frame shown inside a gap of ``who``'s path: no view, the labels and what happened."""
    w, h = size_px
    said = (f"NOT FOLLOWED: {who} seen by no camera {gap[0]:.3f}-{gap[1]:.3f} s (hidden, or "
            "between two tracks): no view")  # fmt: skip
    return burn_text(np.full((h, w, 3), GAP_GREY, np.uint8), [*lines, said])


def is_stale(t_s: float, entry: Entry, spacing_s: float) -> bool:
    """The model shown at ``t_s`` is older than the case's spacing: not of this instant."""
    return t_s - entry.t_s > spacing_s + STALE_SLACK_S


def frame_label(
    t_s: float, path_name: str, entry: Entry, spacing_s: float, clock: CaseClock | None = None
) -> list[str]:
    """The burned-in lines: the date, time of day and case id (given the case's ``clock``); the
    case time, path and model; and ``STALE`` with the model's age when it is older than the
    case's spacing (the picture is not of this instant)."""
    lines = [clock.stamp(t_s)] if clock is not None else []
    lines.append(f"case time {timecode(t_s)}  {path_name}  model {entry.name}")
    if is_stale(t_s, entry, spacing_s):
        age_s = t_s - entry.t_s
        lines.append(f"STALE: model {age_s:.3f} s old (case every {spacing_s:.3f} s)")
    return lines


def replay(
    folder: Path,
    path: CameraPath,
    out: Path,
    config: ReplayConfig,
    progress=None,
    identity: Identity | None = None,
) -> ReplayStats:
    """``path`` through the case in ``folder`` into the MP4 ``out``; with ``config.pip`` or the
    grid layout the session's real frames are read with ``identity`` (a sealed session's
    recipient)."""
    models = CaseModels(folder, identity)  # a sealed session's case opens with it
    times = frame_times(path, models, config)
    order = [models.entry_at(float(t)) for t in times]
    gaps = [path.gap_at(float(t)) for t in times]
    seen = [t for t, gap in zip(times, gaps, strict=True) if gap is None]
    rendered = [e for e, gap in zip(order, gaps, strict=True) if gap is None]
    raster = case_raster(folder, config.near_m, config.device)
    clock = CaseClock.for_case(folder, pick_zone(config.timezone))
    real_wanted = config.pip or config.layout == "grid"
    real = RealCameras(models, identity, clock) if real_wanted else None
    grid = []
    if real is not None and config.layout == "grid":
        eyes = np.array([path.pose(float(t)).centre_m for t in (seen or times)])
        grid = real.nearest(eyes, GRID_CAMERAS)
    t_start, stale = time.perf_counter(), 0
    try:
        with (
            ModelSource(models, rendered, preload=config.preload) as source,
            Mp4Writer(out, config.video_size_px, config.fps) as video,
            ReplayObserved(
                folder,
                out,
                config.size_px,
                config.fps,
                case_raster(folder, device=config.device),
                enabled=config.observed,
            ) as observed,  # fmt: skip
        ):
            for k, (t, entry, gap) in enumerate(zip(times, order, gaps, strict=True)):
                label = frame_label(float(t), path.name, entry, models.spacing_s, clock)
                if gap is not None:
                    shown = gap_card(config.size_px, label, gap, path.name)
                    observed.card(shown)
                    if real is not None and grid:
                        shown = grid_layout(shown, [real.sensor_frame(s, float(t)) for s in grid])
                    video.write(shown)
                    if progress is not None:
                        progress(k + 1, len(times))
                    continue
                camera = path.camera(float(t), config.size_px)
                rgb, _, alpha = render_view(source.get(entry), camera, raster)
                observed.add(float(t), entry, source.get(entry), camera, rgb, raster)
                stale += is_stale(float(t), entry, models.spacing_s)
                shown = burn_text(show_no_data(rgb, alpha), label)
                shown = no_data_legend(shown)
                if real is not None and config.pip:
                    pip = real.frame(camera.pose.centre_m, float(t))
                    if pip is not None:
                        shown = paste_pip(shown, *pip)
                if real is not None and grid:
                    shown = grid_layout(shown, [real.sensor_frame(s, float(t)) for s in grid])
                video.write(shown)
                if progress is not None:
                    progress(k + 1, len(times))
            waited, loads = source.waited_s, len({e.name for e in rendered})
    except UserError:
        out.unlink(missing_ok=True)  # never leave half a video that looks whole
        raise
    finally:
        if real is not None:
            real.close()
    return ReplayStats(
        frames=len(times),
        models=loads,
        wall_s=time.perf_counter() - t_start,
        load_wait_s=waited,
        t_from_s=float(times[0]),
        t_to_s=float(times[-1]),
        damaged_images=tuple(real.damaged) if real is not None else (),
        stale_frames=stale,
        spacing_s=models.spacing_s,
        gap_frames=len(times) - len(seen),
    )
