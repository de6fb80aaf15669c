"""Each timestamp's stereo points, from a reconstructed case or straight from a session.

A case (``docs/case.md``) keeps with each done timestamp's model what its stereo pairs saw
(``depth/evidence.py``: every occupied 2 cm cell, and which cameras saw it); they are read through
the case's own loader (``storage.load_observation``), which checks each file against its
checksum (a sealed session's case with the identity given, refused in one line without one),
and the cells a second camera confirms are kept (``seen_twice_cells``: the same test as
``seen_twice``, on the cameras' masks). A case made before the masks were stored is read from
its session when that is still there, else from its stored points unfiltered. A session
(``.h5``, sealed ones opened with ``identity``) is read set by set every ``every_s`` seconds and
its stereo depth computed with the reconstructor's matcher at half scale, keeping the points a
second camera confirms (``seen_twice``; no fusion, no training). The room's floor area is the
box of the rig's camera centres (the cameras hang on the walls) with a margin.
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


def seen_twice_cells(
    points_m: np.ndarray,
    seen_by: np.ndarray,
    cameras: int,
    room_xy_m: tuple[float, float, float, float],
    cell_m: float,
) -> np.ndarray:
    """(M, 3): ``seen_twice`` for stored evidence, whose points carry a bitmask of the cameras
    that saw them (``seen_by``, bit ``i`` for camera ``i`` of ``cameras``) instead of coming in
    one cloud per camera: a point is kept when at least two cameras saw its cube of ``cell_m``
    or its neighbours (one of them may be its own; a point's own cameras all see its cube)."""
    pts = np.asarray(points_m, np.float64).reshape(-1, 3)
    masks = np.asarray(seen_by).reshape(-1).astype(np.uint32)
    lo = np.array([room_xy_m[0], room_xy_m[1], 0.0])
    shape = np.ceil((np.array([room_xy_m[2], room_xy_m[3], SEEN_TWICE_TOP_M]) - lo) / cell_m)
    shape = shape.astype(int)
    cube = np.floor((pts - lo) / cell_m).astype(np.int64)
    inside = np.all((cube >= 0) & (cube < shape), axis=1)
    cube, masks, pts = cube[inside], masks[inside], pts[inside]
    idx = tuple(cube.T)
    grid = np.zeros(shape, np.uint32)  # the cameras that saw each cube, as bits
    for bit in range(cameras):
        has = (masks >> bit) & 1 == 1
        grid[tuple(cube[has].T)] |= np.uint32(1 << bit)
    # with its 26 neighbours: an OR over a 3 x 3 x 3 cube is three OR passes of 3 along the axes
    for axis in range(3):
        spread = grid.copy()
        lead = [slice(None)] * 3
        lag = [slice(None)] * 3
        lead[axis], lag[axis] = slice(1, None), slice(None, -1)
        spread[tuple(lead)] |= grid[tuple(lag)]
        spread[tuple(lag)] |= grid[tuple(lead)]
        grid = spread
    return pts[np.bitwise_count(grid[idx]) >= 2]


class PeopleInputError(ReconstructError, ValueError):
    """Input ``egosurg people`` cannot use; the message says what to give instead."""


@dataclass(frozen=True)
class Source:
    """What ``egosurg people`` reads: the times, the points at each, the room, the session."""

    path: Path
    kind: str  # "case evidence", "case session", "case points" or "session"
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
    stored_first: bool = True,
) -> Source:
    """A case folder (with ``case.json``) or a session file; one clear error otherwise. A case
    is read from the evidence it stores when that names its cameras (``stored_first``), else
    at its timestamps from its session when that is still there (``use_session``), else from
    the points it keeps, unfiltered."""
    from reconstructor.case.index import INDEX_NAME

    path = Path(path)
    if path.is_dir() and (path / INDEX_NAME).is_file():
        return _case_source(path, t_from_s, t_to_s, identity, use_session, stored_first)
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
    stored_first: bool,
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
    room = room_xy(RigCalibration.read(cal_path))
    compact = storage.is_compact(entries[0])
    # a sealed session's case keeps its points sealed: refused here, in one line naming the
    # recipients, without a recipient's identity
    seal = reader_seal(folder, index, identity, "its stereo points") if compact else None
    masked = stored_first and compact and storage.stores_seen_by(folder, entries[0], seal)
    thin = masked and _match_scale(folder) < MATCH_SCALE
    if (not masked or thin) and use_session and session.is_file():
        # a case made before the cameras were stored with each cell (stereo streaks survive in
        # the stored points), or matched coarser than heads need: its own session's four
        # stereo pairs, checked across cameras
        if thin:
            log.info("%s matched stereo at %g scale, too thin for heads: reading its session "
                     "at %g", folder, _match_scale(folder), MATCH_SCALE)  # fmt: skip
        src = _session_source(
            session, identity, 1e-3, cal_path, None, None, [e.set_index for e in entries]
        )
        return dataclasses.replace(src, path=folder, kind="case session")
    if not compact:
        raise PeopleInputError(
            f"{folder} stores no stereo points with its models (a case made before they were "
            "kept): give its session instead, 'egosurg people SESSION.h5 ...'"
        )
    if not masked or thin:
        log.warning(
            "%s: its session %s is not read here and its points %s; finding people in them "
            "(less clean: give the session beside the case for the better answer)",
            folder,
            session,
            "were matched coarser than heads need" if thin else "do not say which cameras saw them",
        )

    def load(k: int) -> np.ndarray:
        seen = storage.load_observation(folder, entries[k], seal)
        if seen is None:
            raise PeopleInputError(
                f"{folder}: {entries[k].name} stores no stereo points; give the session instead"
            )
        if seen.seen_by is None:
            return seen.points_m
        return seen_twice_cells(
            seen.points_m, seen.seen_by, len(seen.cameras), room, SEEN_TWICE_CELL_M
        )

    return Source(
        path=folder,
        kind="case evidence" if masked else "case points",
        times_s=tuple(e.t_s for e in entries),
        session=case_session(folder),
        room_xy_m=room,
        _load=load,
    )


def _match_scale(folder: Path) -> float:
    """The stereo match scale a case was made with (its ``config.toml``; 0 there means the
    resolution's default, half size or more: as fine as ``egosurg people`` matches)."""
    import tomllib

    try:
        table = tomllib.loads((folder / "config.toml").read_text())
        scale = float(table.get("stereo", {}).get("match_scale", 0.0))
    except (OSError, ValueError, TypeError, AttributeError):
        return 1.0  # no readable record: the stored evidence is what there is
    return scale or 1.0


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
