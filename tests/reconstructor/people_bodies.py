"""Point clouds of simple bodies (legs, torso, arms, head) standing in a room with a table, as a
rig's stereo would see them all round: the input of ``reconstructor.people`` without the
simulator, with the truth known exactly."""

from __future__ import annotations

import math

import numpy as np

TABLE = ((-1.0, -0.3, 0.9), (1.0, 0.3, 0.95))  # a box: min corner, max corner


def _ellipsoid(rng, centre, radii, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(centre) + v * np.asarray(radii)


def _segment(rng, a, b, radius, n):
    a, b = np.asarray(a, float), np.asarray(b, float)
    u = rng.uniform(size=(n, 1))
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return a + u * (b - a) + radius * v


def body(rng, xy, facing_rad, height_m=1.75, working=False, n=6000):
    """(N, 3) points of a person at ``xy`` facing ``facing_rad``; the head's centre is at
    ``1.64 * height_m / 1.75``, its top 0.115 m (scaled) above it."""
    s = height_m / 1.75
    c, si = math.cos(facing_rad), math.sin(facing_rad)
    R = np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]])
    parts = []
    for side in (1, -1):
        parts.append(_segment(rng, (0, 0.1 * side, 0.9), (0, 0.1 * side, 0.05), 0.075, n // 8))
        shoulder = np.array([0, 0.21 * side, 1.43])
        if working:
            hand = shoulder + np.array([0.42, -0.03 * side, -0.3])
        else:
            hand = shoulder + np.array([0.05, 0.03 * side, -0.57])
        parts.append(_segment(rng, shoulder, hand, 0.05, n // 12))
    parts.append(_ellipsoid(rng, (0, 0, 1.18), (0.14, 0.22, 0.33), n // 3))
    parts.append(_segment(rng, (0, 0, 1.45), (0, 0, 1.56), 0.055, n // 20))
    parts.append(_ellipsoid(rng, (0, 0, 1.64), (0.1, 0.085, 0.115), n // 6))
    local = np.concatenate(parts) * s
    return local @ R.T + np.array([xy[0], xy[1], 0.0])


def room(rng, n=20000):
    """A floor and a table: what stays."""
    floor = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), np.zeros(n)])
    lo, hi = np.array(TABLE[0]), np.array(TABLE[1])
    top = rng.uniform(lo, hi, size=(n // 2, 3))
    top[:, 2] = hi[2]
    return np.concatenate([floor, top])


def scene(t_s, rng):
    """Two people: one walks along +x at y = 1.5 (0.6 m/s), one works at the table's side,
    facing it (-y), at y = 0.7. Returns (points, truth {name: (head centre (3,), yaw)})."""
    walker_xy = (-2.0 + 0.6 * t_s, 1.5)
    pts = np.concatenate(
        [room(rng), body(rng, walker_xy, 0.0, 1.8), body(rng, (0.3, 0.75), -math.pi / 2, 1.7, True)]
    )
    truth = {
        "walker": (np.array([*walker_xy, 1.64 * 1.8 / 1.75]), 0.0),
        "worker": (np.array([0.3, 0.75, 1.64 * 1.7 / 1.75]), -math.pi / 2),
    }
    return pts + rng.normal(0, 0.004, size=pts.shape), truth
