"""Each timestamp's stereo points, from a reconstructed case or straight from a session.

A case (``docs/case.md``) keeps each done timestamp's fused stereo points beside its model; they
are read through the case's own loader (``storage.load_points``), which checks each file against
its checksum (a sealed session's case with the identity given, refused in one line without
one). A session (``.h5``, sealed ones opened with ``identity``) is read set by set every
``every_s`` seconds and its stereo depth computed with the reconstructor's matcher at quarter
scale, keeping the points a second camera confirms (``seen_twice``; no fusion, no training).
The room's floor area is the box of the rig's camera centres (the cameras hang on the walls)
with a margin.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.session_id import SessionId
from protocol.sealing.keyfiles import Identity
from reconstructor.errors import ReconstructError

log = logging.getLogger(__name__)

ROOM_MARGIN_M = 1.5
SEEN_TWICE_CELL_M = 0.05
MATCH_SCALE = 0.5  # stereo at half the sensor size
SEEN_TWICE_TOP_M = 2.5  # nobody's head is higher


def seen_twice(
    clouds: list[np.ndarray], room_xy_m: tuple[float, float, float, float], cell_m: float
) -> np.ndarray:
    """(M, 3): the points of ``clouds`` (one (N, 3) array per stereo camera) inside the room
    that another camera also saw, within a cube of ``cell_m`` or its neighbours. A wrong stereo
    match puts a streak of points along that camera's rays, where no other camera sees any."""
    from scipy import ndimage

    lo = np.array([room_xy_m[0], room_xy_m[1], 0.0])
    shape = np.ceil((np.array([room_xy_m[2], room_xy_m[3], SEEN_TWICE_TOP_M]) - lo) / cell_m)
    shape = shape.astype(int)
    cubes, grids = [], []
    for pts in clouds:
        cube = np.floor((np.asarray(pts, np.float64) - lo) / cell_m).astype(np.int64)
        inside = np.all((cube >= 0) & (cube < shape), axis=1)
        grid = np.zeros(shape, bool)
        grid[tuple(cube[inside].T)] = True
        cubes.append((cube, inside))
        grids.append(ndimage.binary_dilation(grid, np.ones((3, 3, 3), bool)))
    total = np.asarray(np.sum(grids, axis=0, dtype=np.int8))
    out = []
    for (cube, inside), grid, pts in zip(cubes, grids, clouds, strict=True):
        idx = tuple(cube[inside].T)
        others = total[idx] - grid[idx]
        out.append(np.asarray(pts)[inside][others >= 1])
    return np.concatenate(out, axis=0) if out else np.zeros((0, 3))


class PeopleInputError(ReconstructError, ValueError):
    """Input ``egosurg people`` cannot use; the message says what to give instead."""


@dataclass(frozen=True)
class Source:
    """What ``egosurg people`` reads: the times, the points at each, the room, the session."""

    path: Path
    kind: str  # "case" or "session"
    times_s: tuple[float, ...]
    session: SessionId | None
    room_xy_m: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    _load: object  # callable: index -> (N, 3) points

    def points(self, k: int) -> np.ndarray:
        return self._load(k)  # type: ignore[operator]

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        for k, t in enumerate(self.times_s):
            yield t, self.points(k)


def room_xy(calibration: RigCalibration) -> tuple[float, float, float, float]:
    centres = np.array([s.camera.pose.centre_m for s in calibration.sensors])
    # the cameras hang inside the room's corners; people walk up to the walls behind them
    lo, hi = centres[:, :2].min(axis=0) - ROOM_MARGIN_M, centres[:, :2].max(axis=0) + ROOM_MARGIN_M
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def open_source(
    path: Path | str,
    *,
    identity: Identity | None = None,
    every_s: float = 0.5,
    calibration: Path | str | None = None,
    t_from_s: float | None = None,
    t_to_s: float | None = None,
    use_session: bool = True,
) -> Source:
    """A case folder (with ``case.json``) or a session file; one clear error otherwise. A case
    is read at its timestamps from its session when that is still there (``use_session``),
    else from the fused points it keeps."""
    from reconstructor.case.index import INDEX_NAME

    path = Path(path)
    if path.is_dir() and (path / INDEX_NAME).is_file():
        return _case_source(path, t_from_s, t_to_s, identity, use_session)
    if path.is_file() and path.suffix in (".h5", ".hdf5"):
        return _session_source(path, identity, every_s, calibration, t_from_s, t_to_s)
    if not path.exists():
        raise PeopleInputError(f"{path} does not exist: give a case folder or a session .h5")
    raise PeopleInputError(
        f"{path} is neither a case folder (it has no {INDEX_NAME}) nor a session file (.h5): "
        "give what 'egosurg reconstruct --every ... --out CASE/' made, or the session"
    )


def _within(t: float, t_from_s: float | None, t_to_s: float | None) -> bool:
    return (t_from_s is None or t >= t_from_s - 1e-9) and (t_to_s is None or t <= t_to_s + 1e-9)


def _case_source(
    folder: Path,
    t_from_s: float | None,
    t_to_s: float | None,
    identity: Identity | None,
    use_session: bool,
) -> Source:
    from reconstructor.case import storage
    from reconstructor.case.index import CaseIndex
    from reconstructor.case.sealing import reader_seal
    from reconstructor.replay.session_check import case_session

    index = CaseIndex.read(folder)
    entries = [
        e for e in index.timestamps if e.status == "done" and _within(e.t_s, t_from_s, t_to_s)
    ]
    if not entries:
        raise PeopleInputError(
            f"{folder} has no finished timestamp{' in --from/--to' if t_from_s or t_to_s else ''}"
            f"; run its 'egosurg reconstruct' command to finish it"
        )
    cal_path = folder / "calibration.toml"
    if not cal_path.is_file():
        raise PeopleInputError(f"{folder} has no calibration.toml; restore it from the run")
    session = Path(index.session)
    if use_session and session.is_file():
        # the case's own session: each timestamp's four stereo pairs, checked across cameras,
        # are cleaner than the fused points the case keeps (stereo streaks survive fusion)
        src = _session_source(
            session, identity, 1e-3, cal_path, None, None, [e.set_index for e in entries]
        )
        return dataclasses.replace(src, path=folder, kind="case")
    # a sealed session's case keeps its points sealed: refused here, in one line naming the
    # recipients, without a recipient's identity
    seal = reader_seal(folder, index, identity, "its stereo points")
    log.warning(
        "%s: its session %s is not here; finding people in the fused points the case keeps "
        "(less clean: give the session beside the case for the better answer)",
        folder,
        session,
    )
    if not storage.is_compact(entries[0]):
        raise PeopleInputError(
            f"{folder} stores no stereo points with its models (a case made before they were "
            "kept): give its session instead, 'egosurg people SESSION.h5 ...'"
        )

    def load(k: int) -> np.ndarray:
        points = storage.load_points(folder, entries[k], seal)
        if points is None:
            raise PeopleInputError(
                f"{folder}: {entries[k].name} stores no stereo points; give the session instead"
            )
        return points

    return Source(
        path=folder,
        kind="case",
        times_s=tuple(e.t_s for e in entries),
        session=case_session(folder),
        room_xy_m=room_xy(RigCalibration.read(cal_path)),
        _load=load,
    )


def _session_source(
    path: Path,
    identity: Identity | None,
    every_s: float,
    calibration: Path | str | None,
    t_from_s: float | None,
    t_to_s: float | None,
    set_indices: list[int] | None = None,
) -> Source:
    from protocol.session import SessionReader
    from reconstructor.config import ReconstructConfig
    from reconstructor.data.frames import load_timestamp
    from reconstructor.depth.fill import FillConfig
    from reconstructor.pipeline import stereo_clouds

    cal_path = Path(calibration) if calibration else path.parent / "calibration.toml"
    if not cal_path.is_file():
        raise PeopleInputError(
            f"no calibration for {path}: pass --calibration FILE (or put calibration.toml "
            "beside the session)"
        )
    rig = RigCalibration.read(cal_path)
    with SessionReader(path, identity=identity) as reader:
        reader.require_identity("every image")
        info = reader.info
        set_ns = reader.sets().set_unix_ns
    times = (np.asarray(set_ns, np.int64) - info.started_unix_ns) / 1e9
    chosen: list[int] = list(set_indices or [])
    for k, t in enumerate(times if set_indices is None else ()):
        if _within(float(t), t_from_s, t_to_s) and (
            not chosen or t - times[chosen[-1]] >= every_s - 1e-6
        ):
            chosen.append(k)
    if not chosen:
        raise PeopleInputError(
            f"{path} has no set in --from/--to; 'egosurg session info' lists them"
        )
    config = ReconstructConfig(fill=FillConfig(enabled=False))
    room = room_xy(rig)

    def load(k: int) -> np.ndarray:
        ts = load_timestamp(path, rig, f"set:{chosen[k]}", identity=identity)
        cfg = config.resolved(ts.frames[0].image_rgb.shape[1])
        assert cfg.stereo is not None
        # a head is ~20 cm across: a quarter-scale match still gives it hundreds of points
        stereo = dataclasses.replace(
            cfg.stereo, match_scale=min(cfg.stereo.match_scale, MATCH_SCALE)
        )
        clouds, _ = stereo_clouds(ts, dataclasses.replace(cfg, stereo=stereo))
        return seen_twice([c[0] for c in clouds], room, SEEN_TWICE_CELL_M)

    return Source(
        path=path,
        kind="session",
        times_s=tuple(float(times[k]) for k in chosen),
        session=SessionId(name=info.session_name, started_unix_ns=int(info.started_unix_ns)),
        room_xy_m=room,
        _load=load,
    )
