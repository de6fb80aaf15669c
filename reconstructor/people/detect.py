"""Heads in one timestamp's points: the top of a column that stands clear of what is around it,
with shoulders below it, and the line of the shoulders (a person faces across it).

A detection is a candidate person: where the head is, how high its top is, the shoulder line's
angle (facing is one of its two normals), for each of those two normals how much of the body
(arms, hands) reaches out on that side, and the pitch at which someone facing that way would look
at the raised surface in front of them (``gaze_pitch_rad``). Which normal is the front is decided
over time by ``pose``, which sees the track's motion too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from reconstructor.people.background import Background
from reconstructor.people.config import PeopleConfig
from reconstructor.people.heightmap import Grid, top_heights

HEAD_RADIUS_M = 0.12  # points this close to the head's axis are the head
RING_M = (0.2, 0.35)  # the ring that must lie lower than the head's top
SHOULDER_BAND_M = (0.25, 0.45)  # below the top of the head
SHOULDER_RADIUS_M = 0.35
REACH_RING_M = (0.22, 0.55)  # arms and hands held out in front
REACH_MIN_Z_M = 0.98
COLUMN_RADIUS_M = 0.3  # below this lie the table's top and the patient, not arms
STATIC_RADIUS_M = 0.16
STATIC_BELOW_M = 0.32
DOUBTFUL = 0.9  # a partly hidden body's head: this share of the confidence a track takes


@dataclass(frozen=True)
class Detection:
    head_xy_m: tuple[float, float]
    top_m: float
    shoulder_axis_rad: float  # direction of the shoulder line, modulo pi
    reach_m: tuple[float, float]  # mean reach of the arms on the +normal and -normal sides
    gaze_pitch_rad: tuple[float, float]  # looking at what lies on the +normal / -normal side
    surface_m: tuple[float, float]  # how far the first raised surface is on each side (inf: none)
    confidence: float  # 0..1
    # share of the room's background cubes around the head (within STATIC_RADIUS_M, from
    # STATIC_BELOW_M below its top to one cube above): equipment the background learned in
    # part, rarely a person's head, which moves through space the room leaves free
    static_share: float = 0.0

    def normal_rad(self, side: int) -> float:
        """Facing of side 0 (+normal) or 1 (-normal)."""
        return self.shoulder_axis_rad + (math.pi / 2 if side == 0 else -math.pi / 2)


@dataclass(frozen=True)
class Frame:
    """One timestamp: the height maps of the room without its people (``top_m``: the surfaces
    one looks at) and of the foreground (``top_fg_m``: where heads are looked for), and the
    foreground's points."""

    grid: Grid
    top_m: np.ndarray
    top_fg_m: np.ndarray
    fg_m: np.ndarray  # (M, 3) float32 foreground points
    background: Background  # the room's cubes


def make_frame(
    points_m: np.ndarray, grid: Grid, background: Background, config: PeopleConfig
) -> Frame:
    def heights(p: np.ndarray) -> np.ndarray:
        return top_heights(
            p,
            grid,
            z_min_m=0.05,
            z_max_m=config.head_top_max_m + 0.1,
            min_points=config.min_points_per_cell,
        )

    p = np.asarray(points_m, np.float32).reshape(-1, 3)
    is_fg = background.is_foreground(p)
    fg = p[is_fg]
    return Frame(grid, heights(p[~is_fg]), heights(fg), fg[fg[:, 2] > 0.05], background)


def _disk(radius_cells: float) -> np.ndarray:
    r = math.ceil(radius_cells)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return (xx * xx + yy * yy) <= radius_cells * radius_cells


def detect(frame: Frame, config: PeopleConfig) -> list[Detection]:
    """The people standing in one timestamp, highest head first."""
    grid, top = frame.grid, frame.top_fg_m
    filled = np.where(np.isfinite(top), top, -1.0)
    peak = ndimage.maximum_filter(filled, footprint=_disk(0.14 / grid.cell_m), mode="constant")
    rows, cols = np.nonzero(
        (filled == peak) & (filled >= config.head_top_min_m) & (filled <= config.head_top_max_m)
    )
    order = np.argsort(-filled[rows, cols], kind="stable")
    xs, ys = grid.centres_m()
    out: list[Detection] = []
    for k in order:
        xy = np.array([xs[cols[k]], ys[rows[k]]])
        if any(np.hypot(*(xy - d.head_xy_m)) < config.min_head_separation_m for d in out):
            continue
        found = _person_at(frame, xy, float(filled[rows[k], cols[k]]), config)
        if found is not None:
            out.append(found)
    return out


def _person_at(frame: Frame, xy: np.ndarray, top: float, config: PeopleConfig) -> Detection | None:
    grid = frame.grid
    xs, ys = grid.centres_m()
    r0, r1 = (
        int(np.floor((v - o) / grid.cell_m))
        for v, o in zip(xy[::-1], grid.origin_xy_m[::-1], strict=True)
    )
    span = math.ceil(RING_M[1] / grid.cell_m) + 1
    rs, cs = slice(max(r0 - span, 0), r0 + span + 1), slice(max(r1 - span, 0), r1 + span + 1)
    patch = frame.top_fg_m[rs, cs]
    dist = np.hypot(xs[cs][None, :] - xy[0], ys[rs][:, None] - xy[1])
    ring = (dist >= RING_M[0]) & (dist <= RING_M[1])
    if not ring.any():
        return None
    lower = ~(patch[ring] > top - config.head_drop_m)  # NaN (nothing there) counts as lower
    isolation = float(np.mean(lower))
    if isolation < config.head_isolation_min:
        return None
    p = frame.fg_m
    near = p[np.abs(p[:, 0] - xy[0]) < REACH_RING_M[1]]
    near = near[np.abs(near[:, 1] - xy[1]) < REACH_RING_M[1]]
    r = np.hypot(near[:, 0] - xy[0], near[:, 1] - xy[1])
    head = near[(r < HEAD_RADIUS_M) & (near[:, 2] > top - 0.2)]
    if len(head) < 10:
        return None
    head_xy = head[:, :2].mean(axis=0).astype(np.float64)
    r = np.hypot(near[:, 0] - head_xy[0], near[:, 1] - head_xy[1])
    # a body stands under the head: points at most heights from the knees to the neck
    column = near[r < COLUMN_RADIUS_M, 2]
    counts, _ = np.histogram(column, bins=np.arange(0.4, top - 0.25, 0.1))
    column_share = float(np.mean(counts >= 3)) if len(counts) else 0.0
    # a body partly hidden (legs behind the table or a neighbour): a doubtful head, which only
    # fills a track's gap between two sightings (``track``), never starts or continues one
    partly = column_share < config.min_column_share
    if partly and (config.column_fill_share <= 0 or column_share < config.column_fill_share):
        return None
    near = near[near[:, 2] > REACH_MIN_Z_M]
    r = np.hypot(near[:, 0] - head_xy[0], near[:, 1] - head_xy[1])
    band = (near[:, 2] < top - SHOULDER_BAND_M[0]) & (near[:, 2] > top - SHOULDER_BAND_M[1])
    shoulders = near[band & (r < SHOULDER_RADIUS_M), :2].astype(np.float64)
    if len(shoulders) < 20:
        return None
    centred = shoulders - shoulders.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    major, minor = vectors[:, 1], vectors[:, 0]
    width = np.subtract(*np.percentile(centred @ major, [95, 5]))
    depth = np.subtract(*np.percentile(centred @ minor, [95, 5]))
    if width < config.shoulder_width_min_m or depth < config.shoulder_depth_min_m:
        return None
    axis = float(np.arctan2(major[1], major[0]))
    normal = np.array([-major[1], major[0]])
    reach_pts = near[(r > REACH_RING_M[0]) & (r < REACH_RING_M[1]) & (near[:, 2] < top - 0.45)]
    along = (reach_pts[:, :2] - head_xy) @ normal
    reach = (float(np.sum(np.clip(along, 0, None))) / max(len(along), 1),
             float(np.sum(np.clip(-along, 0, None))) / max(len(along), 1))  # fmt: skip
    centre_z = top - config.crown_to_centre_m
    front, back = (_gaze(frame, head_xy, normal, centre_z, config),
                   _gaze(frame, head_xy, -normal, centre_z, config))  # fmt: skip
    confidence = float(isolation * column_share * min(1.0, len(head) / 60.0))
    if partly:
        confidence = min(confidence, DOUBTFUL * config.match_confidence)
    return Detection(
        static_share=_static_share(frame, head_xy, top),
        head_xy_m=(float(head_xy[0]), float(head_xy[1])),
        top_m=top,
        shoulder_axis_rad=axis,
        reach_m=reach,
        gaze_pitch_rad=(front[0], back[0]),
        surface_m=(front[1], back[1]),
        confidence=confidence,
    )


def _static_share(frame: Frame, head_xy: np.ndarray, top: float) -> float:
    """The share of background cubes in the box round the head (see ``Detection``)."""
    bg = frame.background
    row, col, _ = frame.grid.cells(head_xy[None, :])
    r, c = int(row[0]), int(col[0])
    k = round(STATIC_RADIUS_M / frame.grid.cell_m)
    lo = max(int(np.floor((top - STATIC_BELOW_M) / frame.grid.cell_m)), 0)
    hi = int(np.floor(top / frame.grid.cell_m)) + 1
    block = bg.static[max(r - k, 0) : r + k + 1, max(c - k, 0) : c + k + 1, lo:hi]
    return float(block.mean()) if block.size else 0.0


def _gaze(
    frame: Frame, head_xy: np.ndarray, direction: np.ndarray, centre_z: float, config: PeopleConfig
) -> tuple[float, float]:
    """Pitch (positive down) at which a head centred over ``head_xy`` facing ``direction``
    looks at the middle of the first raised surface of the room in front of it, and how far
    that surface starts (``default_pitch_deg`` and infinity if there is none)."""
    grid = frame.grid
    step = grid.cell_m / 2
    d = np.arange(0.3, config.gaze_reach_m, step)
    pts = head_xy[None, :] + d[:, None] * direction[None, :]
    row, col, inside = grid.cells(pts)
    h = np.full(len(d), np.nan)
    h[inside] = frame.top_m[row[inside], col[inside]]
    surface = (h >= config.work_surface_min_m) & (h <= config.work_surface_max_m)
    if not surface.any():
        return math.radians(config.default_pitch_deg), math.inf
    start = int(np.argmax(surface))
    stop = start
    while stop + 1 < len(d) and surface[stop + 1]:
        stop += 1
    mid_m = 0.5 * (d[start] + d[stop])
    z = float(np.median(h[start : stop + 1]))
    return float(np.arctan2(centre_z - z, mid_m)), float(d[start])
