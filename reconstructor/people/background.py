"""The room without its people: cubes of space that hold points at almost every timestamp.

Walls, cabinets, the table, booms and screens stay where they are; people move. A cube of
``cell_m`` is background when it holds points in at least ``share`` of the timestamps it was
learned from, and so are its neighbours (a static surface's points jitter between neighbouring
cubes): from the case itself (a person who stands still for less than ``1 - share`` of it
stays foreground; one who never moves becomes part of the room), or, instead, from a recording
of the empty room (``--background``), where any cube seen in a third of its sets is background.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from reconstructor.people.heightmap import Grid

Z_MAX_M = 2.2


@dataclass(frozen=True)
class Background:
    grid: Grid
    levels: int
    static: np.ndarray  # (rows, cols, levels) bool

    @classmethod
    def empty(cls, grid: Grid) -> Background:
        levels = int(np.ceil(Z_MAX_M / grid.cell_m))
        return cls(grid, levels, np.zeros((*grid.shape, levels), bool))

    @classmethod
    def learn(cls, grid: Grid, clouds: list[np.ndarray], share: float) -> Background:
        """From ``clouds`` ((N, 3) points of one timestamp each): cubes seen in at least
        ``share`` of them, dilated by one cube."""
        bg = cls.empty(grid)
        counts = np.zeros(bg.static.size, np.int32)
        cube = np.ones((3, 3, 3), bool)
        for points in clouds:
            counts[np.unique(bg.cube_index(points)[1])] += 1
        static = counts.reshape(bg.static.shape) >= max(share * len(clouds), 1)
        return cls(grid, bg.levels, ndimage.binary_dilation(static, cube))

    def cube_index(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask of the points inside the grid, flat cube index of each of those)."""
        p = np.asarray(points_m, np.float64).reshape(-1, 3)
        row, col, inside = self.grid.cells(p[:, :2])
        level = np.floor(p[:, 2] / self.grid.cell_m).astype(np.int64)
        inside &= (level >= 0) & (level < self.levels) & np.isfinite(p).all(axis=1)
        flat = (row[inside] * self.grid.shape[1] + col[inside]) * self.levels + level[inside]
        return inside, flat

    def is_foreground(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) bool: the points that lie inside the grid and in no background cube."""
        p = np.asarray(points_m).reshape(-1, 3)
        inside, flat = self.cube_index(p)
        keep = np.zeros(len(p), bool)
        keep[np.nonzero(inside)[0]] = ~self.static.reshape(-1)[flat]
        return keep
