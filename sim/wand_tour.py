"""Where the simulated operator takes the wand: through every camera's view, as the calibration
report tells a real operator ("move the wand through the edges and corners of its view").

A wand waved only over the table fills the centre of each image and fails the report's coverage
check (9 of 16 cells of a 4x4 grid, 5 inlier observations each) although the poses come out
within about a millimetre. The tour here visits, for each camera, a point in each cell of its
image grid that the operator can reach and that at least one other camera also sees (a wand seen
by one camera alone does not help the calibration), picks the fewest such points that still reach
every coverable cell of every camera, and walks them in a short loop at a hand's pace.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.camera import Camera

GRID = 4  # the report's coverage grid
REACH_Z_M = (0.5, 2.0)  # heights a standing operator can hold the wand at
WALL_CLEARANCE_M = 0.5  # the operator stands behind the wand, inside the room
MAX_RANGE_M = 4.5  # beyond this the 40 mm spheres get too small to find at HD1200
EDGE_MARGIN = 0.04  # of the image size: a sphere on the border is cut and not detected
SPEED_M_S = 1.4  # a calm sweep: a free-running rig's sync error grows with speed
MIN_HOP_S = 0.6  # linger long enough at each point for several frames


@dataclass(frozen=True)
class Tour:
    """(N, 3) world points visited in order (then back to the first), and the time of each."""

    points_m: np.ndarray
    arrive_s: np.ndarray  # (N + 1,) cumulative, from 0; the last is the loop's period

    def position(self, t_s: float) -> np.ndarray:
        """Where the wand's middle sphere is ``t_s`` seconds into the tour (it loops)."""
        period = float(self.arrive_s[-1])
        t = t_s % period
        i = int(np.searchsorted(self.arrive_s, t, side="right") - 1)
        i = min(i, len(self.points_m) - 1)
        a, b = self.points_m[i], self.points_m[(i + 1) % len(self.points_m)]
        u = (t - self.arrive_s[i]) / (self.arrive_s[i + 1] - self.arrive_s[i])
        s = u * u * (3 - 2 * u)  # slow at each point, so a cell gets several frames
        return (1 - s) * a + s * b


def _in_view(cam: Camera, points: np.ndarray) -> np.ndarray:
    px, z = cam.project(points)
    k = cam.intrinsics
    mx, my = EDGE_MARGIN * k.width_px, EDGE_MARGIN * k.height_px
    return (
        (z > 0.3)
        & (z < MAX_RANGE_M)
        & (px[:, 0] >= mx)
        & (px[:, 0] < k.width_px - mx)
        & (px[:, 1] >= my)
        & (px[:, 1] < k.height_px - my)
    )


def _cells(cam: Camera, points: np.ndarray) -> np.ndarray:
    px, _ = cam.project(points)
    k = cam.intrinsics
    col = np.clip((px[:, 0] * GRID / k.width_px).astype(int), 0, GRID - 1)
    row = np.clip((px[:, 1] * GRID / k.height_px).astype(int), 0, GRID - 1)
    return row * GRID + col


def candidate_points(cameras: tuple[Camera, ...], half_room_m: tuple[float, float]) -> np.ndarray:
    """(M, 3) one reachable point per coverable cell of each camera, seen by >= 2 cameras (the
    range along the cell's central ray where the most cameras see it, the middle of that span)."""
    hx, hy = half_room_m[0] - WALL_CLEARANCE_M, half_room_m[1] - WALL_CLEARANCE_M
    ranges = np.arange(0.8, MAX_RANGE_M, 0.05)
    out = []
    for cam in cameras:
        k = cam.intrinsics
        centre = -cam.pose.R.T @ cam.pose.t_m
        for row in range(GRID):
            for col in range(GRID):
                ray = np.array(
                    [
                        ((col + 0.5) * k.width_px / GRID - k.cx_px) / k.fx_px,
                        ((row + 0.5) * k.height_px / GRID - k.cy_px) / k.fy_px,
                        1.0,
                    ]
                )
                d = cam.pose.R.T @ ray
                pts = centre + ranges[:, None] * (d / np.linalg.norm(d))
                ok = (
                    (np.abs(pts[:, 0]) < hx)
                    & (np.abs(pts[:, 1]) < hy)
                    & (pts[:, 2] > REACH_Z_M[0])
                    & (pts[:, 2] < REACH_Z_M[1])
                )
                seen = sum(_in_view(c, pts).astype(int) for c in cameras) * ok
                if seen.max() >= 2:
                    best = np.flatnonzero(seen == seen.max())
                    out.append(pts[best[len(best) // 2]])
    return np.array(out).reshape(-1, 3)


def coverage_tour(
    cameras: tuple[Camera, ...], half_room_m: tuple[float, float], start_m: np.ndarray
) -> Tour:
    """The loop through every camera's view, starting at the point nearest ``start_m``."""
    points = candidate_points(cameras, half_room_m)
    # what each point puts into each camera's grid: (camera, cell) pairs
    covers = [
        {
            (i, int(c))
            for i, cam in enumerate(cameras)
            for c in _cells(cam, p[None])[_in_view(cam, p[None])]
        }
        for p in points
    ]
    wanted = set().union(*covers) if covers else set()
    chosen: list[int] = []
    while wanted:  # greedy set cover: the fewest points that reach every coverable cell
        j = max(range(len(points)), key=lambda j: len(covers[j] & wanted))
        chosen.append(j)
        wanted -= covers[j]
    pts = points[chosen]
    order = [int(np.argmin(np.linalg.norm(pts - np.asarray(start_m, dtype=float), axis=1)))]
    left = set(range(len(pts))) - set(order)
    while left:  # nearest neighbour: a short walk
        j = min(left, key=lambda j: float(np.linalg.norm(pts[j] - pts[order[-1]])))
        order.append(j)
        left.remove(j)
    pts = pts[order]
    hops = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
    arrive = np.concatenate([[0.0], np.cumsum(np.maximum(hops / SPEED_M_S, MIN_HOP_S))])
    return Tour(points_m=pts, arrive_s=arrive)
