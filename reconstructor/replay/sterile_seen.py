"""Seen empty: whether a camera saw *through* a voxel of a field's region at a timestamp.

A camera sees the first surface along each of its rays, so a cell it saw at range r says the
ray is empty up to r. At timestamp t, camera c sees through voxel V when c saw a cell along the
ray from c through V that lies farther than V by more than V's half-diagonal and the far cell's
depth noise (``SterileConfig.seen_margin_sigmas`` times the matcher's disparity noise times
the cell's metres per pixel of disparity). Over a case, the share of timestamps at which V is
seen through says what V is: air that a hand or an arm entered (seen empty whenever it left), or
a surface that stereo finds only sometimes (the drape's hanging side, the table's padding),
which no camera ever sees through. At the same timestamp, a point in a voxel that a camera sees
through is a smear: a wrong match in the air in front of what that camera saw.

Rays are binned by direction from each camera (``bin_rad`` squares of azimuth and elevation,
about a 2 cm stored cell at 3 m): a bin's range is the nearest cell the camera saw in it, so a
bin that straddles an edge counts as its nearer surface, and a bin with no cell says nothing
(not seen through). ``through_reference`` is the slow, obvious twin of ``through``
(``tests/reconstructor/test_sterile_seen.py`` compares them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BIN_RAD = 0.01  # a 3 cm square at 3 m; a stored cell is 2 cm
_SPAN = 1 << 12  # bins per turn of azimuth or elevation index range (2*pi / 0.01 < 4096)


@dataclass(frozen=True)
class Sight:
    """One timestamp's stored evidence with its cameras: ``points_m`` (M, 3), ``m_per_px``
    (M,) or None, ``seen_by`` (M,) bitmask (bit ``i``: ``centres_m[i]``), ``centres_m`` (C, 3)
    each stereo camera's left-sensor centre."""

    points_m: np.ndarray
    m_per_px: np.ndarray | None
    seen_by: np.ndarray
    centres_m: np.ndarray


def _bin_keys(dirs: np.ndarray, bin_rad: float) -> np.ndarray:
    """(N,) int64 direction bins of (N, 3) unit vectors: azimuth and elevation squares."""
    az = np.floor((np.arctan2(dirs[:, 1], dirs[:, 0]) + np.pi) / bin_rad).astype(np.int64)
    el = np.floor((np.arcsin(np.clip(dirs[:, 2], -1, 1)) + np.pi) / bin_rad).astype(np.int64)
    return az * _SPAN + el


def _ranges(points_m: np.ndarray, centre_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = points_m - centre_m
    r = np.linalg.norm(d, axis=1)
    return d / np.maximum(r, 1e-9)[:, None], r


def through(
    sight: Sight, voxels_m: np.ndarray, half_m: float, noise_px: float, sigmas: float,
    bin_rad: float = BIN_RAD,
) -> np.ndarray:  # fmt: skip
    """(V,) uint32 bitmask of the cameras that see through each voxel centre ``voxels_m``
    (V, 3): a cell in the voxel's ray bin, its nearest, farther than the voxel by more than
    ``half_m`` plus ``sigmas`` times ``noise_px`` times that cell's metres per pixel."""
    out = np.zeros(len(voxels_m), np.uint32)
    noise = sight.m_per_px if sight.m_per_px is not None else np.zeros(len(sight.points_m))
    for c, centre in enumerate(np.asarray(sight.centres_m, float)):
        mine = (sight.seen_by.astype(np.int64) >> c) & 1 == 1
        if not mine.any():
            continue
        dirs, r = _ranges(sight.points_m[mine], centre)
        keys = _bin_keys(dirs, bin_rad)
        order = np.lexsort((r, keys))  # by bin, nearest first
        keys, r, m = keys[order], r[order], noise[mine][order]
        first = np.r_[True, keys[1:] != keys[:-1]]
        keys, r, m = keys[first], r[first], m[first]
        vdirs, vr = _ranges(voxels_m, centre)
        vkeys = _bin_keys(vdirs, bin_rad)
        at = np.clip(np.searchsorted(keys, vkeys), 0, len(keys) - 1)
        hit = keys[at] == vkeys
        beyond = r[at] > vr + half_m + sigmas * noise_px * m[at]
        out[hit & beyond] |= np.uint32(1 << c)
    return out


def through_reference(
    sight: Sight, voxels_m: np.ndarray, half_m: float, noise_px: float, sigmas: float,
    bin_rad: float = BIN_RAD,
) -> np.ndarray:  # fmt: skip
    """``through``, one voxel, camera and cell at a time (slow: for tests)."""
    out = np.zeros(len(voxels_m), np.uint32)
    noise = sight.m_per_px if sight.m_per_px is not None else np.zeros(len(sight.points_m))
    for v, voxel in enumerate(voxels_m):
        for c, centre in enumerate(sight.centres_m):
            d = voxel - centre
            vr = float(np.linalg.norm(d))
            vbin = _bin_of(d / vr, bin_rad)
            nearest = None
            for p, mask, m in zip(sight.points_m, sight.seen_by, noise, strict=True):
                if not (int(mask) >> c) & 1:
                    continue
                e = p - centre
                r = float(np.linalg.norm(e))
                if _bin_of(e / r, bin_rad) == vbin and (nearest is None or r < nearest[0]):
                    nearest = (r, float(m))
            if nearest is not None and nearest[0] > vr + half_m + sigmas * noise_px * nearest[1]:
                out[v] |= 1 << c
    return out


def _bin_of(unit: np.ndarray, bin_rad: float) -> tuple[int, int]:
    az = np.arctan2(unit[1], unit[0]) + np.pi
    el = np.arcsin(min(1.0, max(-1.0, unit[2]))) + np.pi
    return int(np.floor(az / bin_rad)), int(np.floor(el / bin_rad))


@dataclass(frozen=True)
class Freespace:
    """Which voxels of a region some camera saw through, timestamp by timestamp."""

    counts: np.ndarray  # (X, Y, Z) int32: timestamps at which each voxel was seen through
    times_s: np.ndarray  # (T,)
    through: list[np.ndarray]  # per timestamp, the flat indices of the voxels seen through
    # per timestamp, (sorted flat indices of the voxels holding a point, each one's bitmask of
    # the cameras that saw a point in it); None: not known
    cameras: list[tuple[np.ndarray, np.ndarray]] | None = None

    def seen_empty(self, voxels: np.ndarray, t_s: float, window_s: float) -> np.ndarray | None:
        """(N,) share of the timestamps more than ``window_s`` from ``t_s`` at which each of
        ``voxels`` ((N, 3) indices) was seen through; None when no timestamp is that far (the
        span cannot say)."""
        flat = np.ravel_multi_index(voxels.T, self.counts.shape)
        near = np.abs(self.times_s - t_s) <= window_s
        hits = self.counts.ravel()[flat].astype(np.int64)
        for k in np.nonzero(near)[0]:
            hits -= np.isin(flat, self.through[k])
        others = int((~near).sum())
        return hits / others if others else None

    def cameras_of(self, voxels: np.ndarray, t_s: float) -> int | None:
        """How many cameras saw a point in any of ``voxels`` ((N, 3) indices) at ``t_s``; None
        when not known. A wrong stereo match lies along one camera's rays: no other sees it."""
        if self.cameras is None:
            return None
        flat, masks = self.cameras[int(np.argmin(np.abs(self.times_s - t_s)))]
        want = np.ravel_multi_index(voxels.T, self.counts.shape)
        at = np.clip(np.searchsorted(flat, want), 0, max(len(flat) - 1, 0))
        hit = masks[at][flat[at] == want] if len(flat) else masks[:0]
        return bin(int(np.bitwise_or.reduce(hit, initial=0))).count("1")

    def now(self, voxels: np.ndarray, t_s: float) -> np.ndarray:
        """(N,) bool: each of ``voxels`` seen through at ``t_s`` itself."""
        k = int(np.argmin(np.abs(self.times_s - t_s)))
        return np.isin(np.ravel_multi_index(voxels.T, self.counts.shape), self.through[k])


def freespace(region, sights: list[Sight], times_s: list[float]) -> Freespace:
    """The ``Freespace`` of ``region`` (``sterile.Region``) over each timestamp's sight."""
    cfg = region.config
    idx = np.indices(region.shape).reshape(3, -1).T
    local = (idx + 0.5) * cfg.voxel_m - region.half_m
    centres = np.asarray(region.box.centre_m) + local @ region.box.rotation.T
    half = cfg.voxel_m * np.sqrt(3) / 2
    counts = np.zeros(region.shape, np.int32)
    seen, cameras = [], []
    for s in sights:
        flat = np.flatnonzero(
            through(s, centres, half, cfg.disparity_noise_px, cfg.seen_margin_sigmas)
        )
        counts.ravel()[flat] += 1
        seen.append(flat)
        near = region.holds(s.points_m)
        cells = np.ravel_multi_index(region.voxels(s.points_m[near]).T, region.shape)
        keys, inverse = np.unique(cells, return_inverse=True)
        masks = np.zeros(len(keys), np.uint32)
        np.bitwise_or.at(masks, inverse.ravel(), s.seen_by[near].astype(np.uint32))
        cameras.append((keys, masks))
    return Freespace(counts, np.asarray(times_s, float), seen, cameras)
