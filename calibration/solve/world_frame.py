"""The world frame: the floor at z = 0, from the sets where the wand lies on the floor.

Detection: a *still run* is a stretch of at least ``min_still_s`` where the wand's image stays
within ``tolerance_px`` of where it was at the run's start. A still run is on the floor if the
wand lies level in it and it is the lowest thing seen: no more than ``max_height_m`` above the
lowest still run, which itself is within ``max_height_m`` of the lowest 1 % of all sphere
heights. "Up" for these tests comes from the cameras: wall-mounted cameras are hung level, so
their x axes are horizontal, and the cameras are above the wand.

The floor plane: sphere centres on the floor are one radius above it. Centres from two or more
placements that do not lie on one line span the plane and fix its normal exactly. A wand lying
in one place gives only a line, which leaves the plane free to turn about it; the turn is then
taken from the level cameras (the normal closest to perpendicular to every camera's x axis), and
``FloorFrame.normal_source`` says so. Lay the wand in two directions to need no such assumption.

Axes: z up (towards the cameras), x along the wand on the floor (first towards last sphere, in
its first placement), origin on the floor below the first sphere. ``x_world = R @ x_ref + t``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FloorFrame:
    R: np.ndarray  # (3, 3) reference-to-world rotation
    t: np.ndarray  # (3,)
    floor_sets: np.ndarray  # (F,) set indices with the wand on the floor
    normal_source: str  # "wand placements" or "wand line + level cameras"
    plane_rms_mm: float  # sphere centres' RMS distance from the fitted plane


def level_up(cam_R: np.ndarray, cam_centres: np.ndarray, below: np.ndarray) -> np.ndarray | None:
    """The direction perpendicular to every camera's x axis, signed towards the cameras.

    ``cam_R`` (C, 3, 3) world-to-camera rotations (a camera's x axis is ``R[0]``); ``below``
    (3,) a point under the cameras. None if the x axes do not pin a direction down.
    """
    axes = cam_R[:, 0, :]
    _, s, vt = np.linalg.svd(axes)
    if len(axes) < 2 or s[1] < 0.2 * s[0]:
        return None
    up = vt[-1]
    if np.mean((cam_centres - below) @ up) < 0:
        up = -up
    return up


def still_runs(
    points_px: np.ndarray, t_s: np.ndarray, *, min_still_s: float, tolerance_px: float
) -> list[np.ndarray]:
    """Runs of sets where the wand does not move, judged in the images (detection noise is a
    tenth of a pixel, where a far camera's triangulation wanders by centimetres).

    ``points_px`` (N, S, 3, 2), NaN where unseen. A set continues a run if, over the sensors and
    spheres seen in both, the median pixel distance to the run's first set is within
    ``tolerance_px`` (a median, so one outlier does not end a run). A gap of more than 0.5 s
    ends a run."""
    valid = np.flatnonzero(np.isfinite(points_px).all(axis=3).any(axis=(1, 2)))
    valid = valid[np.argsort(t_s[valid], kind="stable")]
    runs: list[np.ndarray] = []
    i = 0
    while i < len(valid):
        start = points_px[valid[i]]
        j = i + 1
        while j < len(valid) and t_s[valid[j]] - t_s[valid[j - 1]] <= 0.5:
            moved = np.linalg.norm(points_px[valid[j]] - start, axis=2)
            moved = moved[np.isfinite(moved)]
            if not len(moved) or np.median(moved) > tolerance_px:
                break
            j += 1
        run = valid[i:j]
        if t_s[run[-1]] - t_s[run[0]] >= min_still_s and len(run) >= 3:
            runs.append(run)
        i = j
    return runs


def find_floor(
    centres: np.ndarray,
    points_px: np.ndarray,
    t_s: np.ndarray,
    cam_R: np.ndarray,
    cam_centres: np.ndarray,
    radius_m: float,
    *,
    min_still_s: float,
    tolerance_px: float,
    max_height_m: float,
    max_tilt_deg: float,
) -> FloorFrame | None:
    """The floor frame, or None. ``centres`` (N, 3, 3) the solved sphere centres in the reference
    frame (NaN where unknown), ``points_px`` (N, S, 3, 2) the observations, ``t_s`` (N,) set
    times; ``cam_R`` (C, 3, 3) and ``cam_centres`` (C, 3) the cameras in the same frame."""
    valid = np.isfinite(centres).all(axis=(1, 2))
    if valid.sum() < 3:
        return None
    up = level_up(cam_R, cam_centres, np.median(centres[valid].reshape(-1, 3), axis=0))
    if up is None:
        log.info("floor: the cameras' x axes do not give a vertical; no floor frame")
        return None
    runs = [
        r[valid[r]]
        for r in still_runs(points_px, t_s, min_still_s=min_still_s, tolerance_px=tolerance_px)
    ]
    runs = [r for r in runs if len(r) >= 3]
    if not runs:
        log.info("floor: the wand never lies still for %.1f s; no floor frame", min_still_s)
        return None
    heights = centres[valid] @ up
    lowest_seen = float(np.percentile(heights, 1))
    sin_tilt = np.sin(np.radians(max_tilt_deg))
    level = []
    for run in runs:
        c = centres[run].mean(axis=0)
        d = (c[2] - c[0]) / np.linalg.norm(c[2] - c[0])
        if abs(d @ up) <= sin_tilt:
            level.append((float((c @ up).mean()), run))
    if not level:
        log.info("floor: no still run with the wand lying level; no floor frame")
        return None
    lowest = min(h for h, _ in level)
    if lowest > lowest_seen + max_height_m:
        log.info(
            "floor: the lowest still wand lies %.2f m above the lowest wand position seen, so "
            "it was not on the floor; no floor frame",
            lowest - lowest_seen,
        )
        return None
    floor_runs = [run for h, run in level if h <= lowest + max_height_m]
    sets = np.sort(np.concatenate(floor_runs))
    pts = centres[sets].reshape(-1, 3)
    mean = pts.mean(axis=0)
    _, s, vt = np.linalg.svd(pts - mean)
    if s[1] / np.sqrt(len(pts)) > 0.05:  # the centres span a plane, not only a line
        normal = vt[2] * np.sign(vt[2] @ up)
        source = "wand placements"
    else:
        line = vt[0]
        normal = up - (up @ line) * line
        normal /= np.linalg.norm(normal)
        source = "wand line + level cameras"
    rms = float(np.sqrt(np.mean(((pts - mean) @ normal) ** 2)))
    first_run = floor_runs[0]  # x and the origin follow the wand's first placement
    first = centres[first_run, 0].mean(axis=0)
    wand_dir = (centres[first_run, 2] - centres[first_run, 0]).mean(axis=0)
    x = wand_dir - (wand_dir @ normal) * normal
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(normal, x), normal])
    origin = first - (first - mean) @ normal * normal - radius_m * normal
    log.info(
        "floor: %d sets in %d still runs, normal from %s, plane RMS %.2f mm",
        len(sets),
        len(floor_runs),
        source,
        1000 * rms,
    )
    return FloorFrame(R, -R @ origin, sets, source, 1000 * rms)
