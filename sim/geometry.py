"""Small triangle-mesh builders for the simulated room.

Winding does not matter: shading flips each normal to face the viewing ray. Meshes are plain numpy
arrays so they can be transformed and merged cheaply before they go to open3d's raycaster.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    """vertices: (N, 3) float32 metres; triangles: (M, 3) int32."""

    vertices: np.ndarray
    triangles: np.ndarray

    def transformed(self, R: np.ndarray, t: np.ndarray) -> Mesh:
        v = self.vertices.astype(np.float64) @ np.asarray(R).T + np.asarray(t)
        return Mesh(v.astype(np.float32), self.triangles)

    @staticmethod
    def merge(meshes: list[Mesh]) -> Mesh:
        if not meshes:
            return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
        verts, tris, offset = [], [], 0
        for m in meshes:
            verts.append(m.vertices)
            tris.append(m.triangles + offset)
            offset += len(m.vertices)
        return Mesh(np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.int32))


def rot_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def box(
    centre: tuple[float, float, float] | np.ndarray,
    size: tuple[float, float, float] | np.ndarray,
    R: np.ndarray | None = None,
) -> Mesh:
    """An axis-aligned box of full extents ``size``, rotated by ``R`` about its centre."""
    sx, sy, sz = (np.asarray(size, dtype=np.float64) / 2).tolist()
    corners = np.array(
        [[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)], dtype=np.float64
    )
    # corner index = 4*ix + 2*iy + iz
    faces = [
        (0, 1, 3, 2),  # -x
        (4, 6, 7, 5),  # +x
        (0, 4, 5, 1),  # -y
        (2, 3, 7, 6),  # +y
        (0, 2, 6, 4),  # -z
        (1, 5, 7, 3),  # +z
    ]
    tris = []
    for a, b, c, d in faces:
        tris += [(a, b, c), (a, c, d)]
    mesh = Mesh(corners.astype(np.float32), np.array(tris, dtype=np.int32))
    return mesh.transformed(np.eye(3) if R is None else R, np.asarray(centre, dtype=np.float64))


def room_box(x_m: tuple[float, float], y_m: tuple[float, float], z_m: tuple[float, float]) -> Mesh:
    """The inside of a room: a box, subdivided so no triangle is huge (keeps the BVH balanced)."""
    centre = ((x_m[0] + x_m[1]) / 2, (y_m[0] + y_m[1]) / 2, (z_m[0] + z_m[1]) / 2)
    size = (x_m[1] - x_m[0], y_m[1] - y_m[0], z_m[1] - z_m[0])
    return box(centre, size)


def cylinder(
    p0: np.ndarray | tuple[float, ...],
    p1: np.ndarray | tuple[float, ...],
    radius: float,
    segments: int = 20,
    capped: bool = True,
) -> Mesh:
    """A cylinder of ``radius`` from point ``p0`` to point ``p1``."""
    a = np.asarray(p0, dtype=np.float64)
    b = np.asarray(p1, dtype=np.float64)
    axis = b - a
    length = float(np.linalg.norm(axis))
    if length < 1e-9:
        raise ValueError("cylinder needs two distinct end points")
    ring = unit_circle(axis / length, segments)
    verts = np.concatenate([a + radius * ring, b + radius * ring, [a, b]])
    n = segments
    tris = []
    for i in range(n):
        j = (i + 1) % n
        tris += [(i, j, n + j), (i, n + j, n + i)]
        if capped:
            tris += [(2 * n, j, i), (2 * n + 1, n + i, n + j)]
    return Mesh(verts.astype(np.float32), np.array(tris, dtype=np.int32))


def ellipsoid(
    centre: np.ndarray | tuple[float, ...],
    radii: np.ndarray | tuple[float, ...],
    R: np.ndarray | None = None,
    rings: int = 16,
    segments: int = 24,
    z_min_frac: float = -1.0,
) -> Mesh:
    """An ellipsoid; ``z_min_frac`` > -1 cuts it below that fraction of the z radius (a cap)."""
    theta = np.linspace(np.arccos(np.clip(z_min_frac, -1, 1)), 0.0, rings + 1)  # bottom -> top
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    pts = np.stack(
        [
            st * np.cos(phi)[None],
            st * np.sin(phi)[None],
            np.broadcast_to(ct, (rings + 1, segments)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    pts = pts * np.asarray(radii, dtype=np.float64)
    return _closed_grid_mesh(pts, rings, segments, centre, R)


def torus_arc(
    centre: np.ndarray | tuple[float, ...],
    major_m: float,
    minor_m: float,
    start_rad: float,
    end_rad: float,
    R: np.ndarray | None = None,
    segments: int = 48,
    sides: int = 14,
) -> Mesh:
    """Part of a torus in the local x-z plane (a C-arm), rotated by ``R`` about ``centre``."""
    u = np.linspace(start_rad, end_rad, segments + 1)
    v = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    cu, su = np.cos(u)[:, None], np.sin(u)[:, None]
    cv, sv = np.cos(v)[None], np.sin(v)[None]
    x = (major_m + minor_m * cv) * cu
    z = (major_m + minor_m * cv) * su
    y = np.broadcast_to(minor_m * sv, x.shape)
    pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    return _closed_grid_mesh(pts, segments, sides, centre, R)


def unit_circle(axis_unit: np.ndarray, n: int) -> np.ndarray:
    """(n, 3): ``n`` points, evenly spaced from angle 0, on the unit circle about the unit
    vector ``axis_unit``. Angle 0 lies along ``helper x axis_unit``, where ``helper`` is the world
    x axis unless ``axis_unit`` is close to it (then y), so the frame never degenerates."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis_unit[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis_unit)
    x /= np.linalg.norm(x)
    y = np.cross(axis_unit, x)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y


def _closed_grid_mesh(
    pts: np.ndarray,
    rows: int,
    cols: int,
    centre: np.ndarray | tuple[float, ...],
    R: np.ndarray | None,
) -> Mesh:
    """A surface from ``(rows + 1) * cols`` local points laid out row by row, each row closed
    on itself (column ``cols - 1`` joins column 0), moved by ``R`` and ``centre``."""
    tris = []
    for r in range(rows):
        for c in range(cols):
            a = r * cols + c
            b = r * cols + (c + 1) % cols
            d = (r + 1) * cols + c
            tris += [(a, b, b + cols), (a, b + cols, d)]
    mesh = Mesh(pts.astype(np.float32), np.array(tris, dtype=np.int32))
    return mesh.transformed(np.eye(3) if R is None else R, np.asarray(centre, dtype=np.float64))
