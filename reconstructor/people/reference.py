"""Slow, obvious twins of the fast kernels (tests compare them on the same inputs)."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from reconstructor.people.heightmap import Grid


def top_heights_reference(
    points_m: np.ndarray, grid: Grid, *, z_min_m: float, z_max_m: float, min_points: int
) -> np.ndarray:
    """``heightmap.top_heights`` one point at a time, with dictionaries (cubes below
    ``z_min_m`` hold no point, as in the fast one)."""
    cubes: dict[tuple[int, int, int], list[float]] = defaultdict(list)
    for x, y, z in np.asarray(points_m, np.float64).reshape(-1, 3):
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        if not z_min_m <= z < z_max_m:
            continue
        col = math.floor((x - grid.origin_xy_m[0]) / grid.cell_m)
        row = math.floor((y - grid.origin_xy_m[1]) / grid.cell_m)
        if not (0 <= row < grid.shape[0] and 0 <= col < grid.shape[1]):
            continue
        level = math.floor((z - z_min_m) / grid.cell_m)
        cubes[(row, col, level)].append(z)
    out = np.full(grid.shape, np.nan, np.float32)
    for (row, col, level), zs in cubes.items():
        around = sum(
            len(cubes.get((row + i, col + j, level + k), ()))
            for i in (-1, 0, 1)
            for j in (-1, 0, 1)
            for k in (-1, 0, 1)
        )
        if around >= min_points and not out[row, col] >= max(zs):
            out[row, col] = max(zs)
    return out
