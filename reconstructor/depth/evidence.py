"""What the cameras observed at one timestamp: the evidence a case stores beside each model.

The training cloud (``fusion.fuse``) is made for the rasterizer: it mixes in the hole filler's
guessed points and keeps a uniform ``max_points`` subsample, so how much of a hand it keeps
depends on how much else the room holds (filling adds about 230 000 points to a sim frame, and
the cap then keeps 19 % of what stereo saw instead of 25 %). The evidence is kept apart from it:

- only stereo's own points (each depth map's valid pixels), never filled ones;
- every occupied ``cell_m`` cube, at the mean of the points in it: a surface seen is a count of
  cells, about its area over ``cell_m**2``, whatever else the room holds (no cap);
- with each cell, ``m_per_px``: how far the depth of the best camera that saw it moves for one
  pixel of disparity, ``z**2 / (f * B)`` (z the depth in that camera's rectified frame, f its
  focal length in pixels, B its baseline). A reader multiplies it by the matcher's disparity
  noise to get the depth uncertainty of the cell (``sterile``'s margin test).

- with each cell, ``seen_by``: which of the stereo cameras had a point in it, a bitmask (bit
  ``i`` is ``cameras[i]``, the depth maps' names in the order given). A wrong stereo match puts a
  streak of points along ONE camera's rays; a reader keeps what a second camera confirms
  (``people``: ``sources.seen_twice_cells``).

A cell's position is the mean of all the points in it; its ``m_per_px`` is the smallest of them
(the nearest, or the one camera with the longest baseline for its range).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.camera import Pose
from reconstructor.depth.stereo import DepthMap

CELL_M = 0.02  # a hand is about 5 x 10 cells; a 1 cm cell would double the stored bytes
_OFFSET = 1 << 20  # cell indices are shifted by this to be non-negative (+-20 km at 2 cm)
MAX_CAMERAS = 31  # bits of a mask (the model file packs it in 32-bit zigzag: 31 bits)


def mask_dtype(cameras: int) -> type[np.unsignedinteger]:
    """The smallest unsigned type with a bit per camera (uint8 for a rig of up to 8 pairs)."""
    if cameras > MAX_CAMERAS:
        raise ValueError(f"{cameras} stereo cameras: a mask holds at most {MAX_CAMERAS}")
    return np.uint8 if cameras <= 8 else np.uint16 if cameras <= 16 else np.uint32


@dataclass(frozen=True)
class Observed:
    """``points_m`` (M, 3) float64 world metres, one per occupied cell; ``m_per_px`` (M,)
    float64 metres of depth per pixel of disparity of the best camera that saw each cell;
    ``seen_by`` (M,) unsigned bitmask of the cameras that saw each cell (bit ``i`` is
    ``cameras[i]``)."""

    points_m: np.ndarray
    m_per_px: np.ndarray
    seen_by: np.ndarray
    cameras: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.points_m)


def observed_points(
    depths: dict[str, DepthMap], poses: dict[str, Pose], cell_m: float = CELL_M
) -> Observed:
    """The cells the stereo pairs saw: ``depths`` by camera name ("SN<serial>"), ``poses`` the
    world-to-camera pose of each one's left sensor (by the same names; a depth map without a
    pose is an error). Each depth map's valid pixels only: hole filling is not evidence."""
    if cell_m <= 0:
        raise ValueError(f"cell_m {cell_m}: give a positive size in metres")
    cameras = tuple(depths)
    dtype = mask_dtype(len(cameras))
    pts, noise = [], []
    for name, depth in depths.items():
        world, _ = depth.points_in_world(poses[name])
        z = depth.depth_m[depth.valid].astype(np.float64)
        pts.append(world.astype(np.float64))
        noise.append(z**2 / (depth.intrinsics.fx_px * depth.baseline_m))
    if not pts or not sum(len(p) for p in pts):
        return Observed(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype), cameras)
    points = np.concatenate(pts)
    m_per_px = np.concatenate(noise)
    cells = np.floor(points / cell_m).astype(np.int64) + _OFFSET
    key = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
    uniq, inverse = np.unique(key, return_inverse=True)
    counts = np.bincount(inverse, minlength=len(uniq)).astype(np.float64)
    means = np.stack(
        [np.bincount(inverse, points[:, k], len(uniq)) / counts for k in range(3)], axis=1
    )
    best = np.full(len(uniq), np.inf)
    np.minimum.at(best, inverse, m_per_px)
    seen_by = np.zeros(len(uniq), dtype)
    start = 0
    for bit, p in enumerate(pts):
        cells_of = inverse[start : start + len(p)]
        start += len(p)
        hit = np.bincount(cells_of, minlength=len(uniq)) > 0
        seen_by[hit] |= dtype(1 << bit)
    return Observed(means, best, seen_by, cameras)


def observed_of_reconstruction(depths: dict[str, DepthMap], stereo_pairs) -> Observed:
    """``observed_points`` with each depth map's pose taken from the timestamp's stereo pairs
    (``Timestamp.stereo_pairs()``: (left, right) frames; the depth maps are named after the
    left's serial)."""
    poses = {f"SN{left.camera_serial}": left.camera.pose for left, _ in stereo_pairs}
    return observed_points({n: d for n, d in depths.items() if n in poses}, poses)
