"""The points of one timestamp as a top-height map over the floor (z up, floor at 0).

Each cell of ``cell_m`` holds the height of the highest point above it, counting only points in
cubes of ``cell_m`` whose 3 x 3 x 3 neighbourhood of cubes holds at least ``min_points`` points
(stereo outliers, scattered in the air, raise no column; a surface, dense, does). Heads are
the tops of columns; the height map is what ``detect`` looks at.
``reference.top_heights_reference`` is this kernel's slow, obvious twin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class Grid:
    """Cells of ``cell_m`` over ``origin_xy_m`` .. ``origin_xy_m + shape * cell_m``."""

    origin_xy_m: tuple[float, float]
    shape: tuple[int, int]  # (rows along y, columns along x)
    cell_m: float

    @classmethod
    def covering(cls, xy_min_m: np.ndarray, xy_max_m: np.ndarray, cell_m: float) -> Grid:
        lo = np.asarray(xy_min_m, np.float64)
        n = np.maximum(np.ceil((np.asarray(xy_max_m, np.float64) - lo) / cell_m), 1).astype(int)
        return cls((float(lo[0]), float(lo[1])), (int(n[1]), int(n[0])), float(cell_m))

    def cells(self, xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, column, inside) of (N, 2) points."""
        ij = np.floor((np.asarray(xy_m) - self.origin_xy_m) / self.cell_m).astype(np.int64)
        col, row = ij[:, 0], ij[:, 1]
        inside = (row >= 0) & (row < self.shape[0]) & (col >= 0) & (col < self.shape[1])
        return row, col, inside

    def centres_m(self) -> tuple[np.ndarray, np.ndarray]:
        """(x (cols,), y (rows,)) of the cell centres."""
        x = self.origin_xy_m[0] + (np.arange(self.shape[1]) + 0.5) * self.cell_m
        y = self.origin_xy_m[1] + (np.arange(self.shape[0]) + 0.5) * self.cell_m
        return x, y


def top_heights(
    points_m: np.ndarray, grid: Grid, *, z_min_m: float, z_max_m: float, min_points: int
) -> np.ndarray:
    """(rows, cols) float32: the highest counted point's z above each cell, NaN where none.

    ``points_m`` (N, 3) world metres; points outside ``z_min_m`` .. ``z_max_m`` or the grid are
    left out; a point counts when the 27 cubes of ``grid.cell_m`` around its own hold
    ``min_points`` or more points together."""
    p = np.asarray(points_m, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1) & (p[:, 2] >= z_min_m) & (p[:, 2] < z_max_m)]
    row, col, inside = grid.cells(p[:, :2])
    p, row, col = p[inside], row[inside], col[inside]
    out = np.full(grid.shape, np.nan, np.float32)
    if len(p) == 0:
        return out
    level = np.floor((p[:, 2] - z_min_m) / grid.cell_m).astype(np.int64)
    levels = int(level.max()) + 1
    column = row * grid.shape[1] + col
    counts = np.zeros((*grid.shape, levels), np.float32)
    np.add.at(counts, (row, col, level), 1.0)
    near = ndimage.uniform_filter(counts, size=3, mode="constant") * 27
    keep = near[row, col, level] >= min_points - 0.5
    flat = np.full(grid.shape[0] * grid.shape[1], -np.inf)
    np.maximum.at(flat, column[keep], p[keep, 2])
    out.reshape(-1)[:] = np.where(np.isfinite(flat), flat, np.nan)
    return out
