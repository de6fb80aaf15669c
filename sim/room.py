"""The static operating room: walls, floor, ceiling lights, table, patient and equipment.

World frame: metres, z up, the origin on the floor under the centre of the OR table, x along the
table (head end at -x), y across it. The room spans x in [-3.5, 3.5], y in [-3, 3], z in [0, 3].
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sim.errors import OutsideRoomError
from sim.geometry import Mesh, box, cylinder, ellipsoid, room_box, rot_x, rot_z, torus_arc


@dataclass(frozen=True, kw_only=True)
class RoomSpec:
    length_x_m: float = 7.0
    width_y_m: float = 6.0
    height_z_m: float = 3.0

    def __post_init__(self) -> None:
        for name in ("length_x_m", "width_y_m", "height_z_m"):
            v = getattr(self, name)
            if not 2.0 <= v <= 30.0:
                raise ValueError(f"RoomSpec.{name}={v} is not a plausible room size (2 to 30 m)")

    @property
    def x_range_m(self) -> tuple[float, float]:
        return (-self.length_x_m / 2, self.length_x_m / 2)

    @property
    def y_range_m(self) -> tuple[float, float]:
        return (-self.width_y_m / 2, self.width_y_m / 2)

    def contains(self, point_m: np.ndarray, margin_m: float = 0.0) -> bool:
        x, y, z = (float(v) for v in np.asarray(point_m).reshape(3))
        hx, hy = self.length_x_m / 2 - margin_m, self.width_y_m / 2 - margin_m
        return abs(x) <= hx and abs(y) <= hy and margin_m <= z <= self.height_z_m - margin_m

    def require_inside(self, point_m: np.ndarray, what: str, margin_m: float = 0.02) -> None:
        if not self.contains(point_m, margin_m):
            p = np.round(np.asarray(point_m, dtype=float).reshape(3), 3).tolist()
            raise OutsideRoomError(
                f"{what} at {p} m is outside the room (x in ±{self.length_x_m / 2:g}, "
                f"y in ±{self.width_y_m / 2:g}, z in 0..{self.height_z_m:g} m, at least "
                f"{margin_m * 100:g} cm from every wall); move it inside"
            )


@dataclass(frozen=True)
class SceneObject:
    """A mesh with one material. ``local_from_world`` maps hit points into the object's own frame
    for texturing, so textures move with people instead of swimming over them."""

    name: str
    mesh: Mesh
    texture: str
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    local_R: np.ndarray = field(default_factory=lambda: np.eye(3))
    local_t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    emission: float = 0.0  # radiance scale for emissive textures


@dataclass(frozen=True)
class Light:
    position_m: np.ndarray
    power: float  # irradiance at 1 m on a facing surface, in radiance units


@dataclass(frozen=True)
class Footprint:
    """A labelled rectangle for the top-down map: centre (x, y), size (dx, dy), yaw."""

    label: str
    centre_xy_m: tuple[float, float]
    size_xy_m: tuple[float, float]
    yaw_rad: float = 0.0


TABLE_TOP_Z_M = 0.92  # top of the mattress
TABLE_CENTRE_XY_M = (0.0, 0.0)


_Add = Callable[..., None]  # add(texture, mesh, tint=white): one more mesh of that material


def build_room(
    room: RoomSpec, *, with_patient: bool, with_mobile_equipment: bool = True
) -> tuple[list[SceneObject], list[Light]]:
    """The static objects (grouped one material per mesh) and the lights."""
    H = room.height_z_m
    parts: dict[tuple[str, tuple[float, float, float]], list[Mesh]] = {}

    def add(texture: str, mesh: Mesh, tint: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> None:
        parts.setdefault((texture, tint), []).append(mesh)

    objects = _shell_objects(room)
    _add_walls_and_table(add, room)
    if with_patient:
        _add_patient(add)
    if with_mobile_equipment:
        _add_mobile_equipment(add)
    objects += _add_monitors(add, H)
    objects += _add_back_table_and_anaesthesia(add)
    panels = [(-2.0, -1.5), (-2.0, 1.5), (2.0, -1.5), (2.0, 1.5)]
    objects += _add_lamps(add, H, panels)

    for (texture, tint), meshes in parts.items():
        objects.append(SceneObject(f"{texture}", Mesh.merge(meshes), texture, tint))

    lights = [Light(np.array([px, py, H - 0.1]), 1.9) for px, py in panels]
    lights.append(Light(np.array([0.15, 0.0, 2.2]), 0.6))
    return objects, lights


def _shell_objects(room: RoomSpec) -> list[SceneObject]:
    """The room's box split by material: floor (-z face), ceiling (+z) and walls."""
    H = room.height_z_m
    shell = room_box(room.x_range_m, room.y_range_m, (0.0, H))
    tri = shell.triangles
    v = shell.vertices[tri]
    zc = v[:, :, 2].mean(axis=1)
    spread_z = np.ptp(v[:, :, 2], axis=1)
    is_floor = (spread_z < 1e-6) & (zc < H / 2)
    is_ceiling = (spread_z < 1e-6) & (zc > H / 2)
    is_wall = ~(is_floor | is_ceiling)
    return [
        SceneObject("floor", Mesh(shell.vertices, tri[is_floor]), "floor"),
        SceneObject("ceiling", Mesh(shell.vertices, tri[is_ceiling]), "ceiling"),
        SceneObject("walls", Mesh(shell.vertices, tri[is_wall]), "wall"),
    ]


def _add_walls_and_table(add: _Add, room: RoomSpec) -> None:
    """A door, a wall of cabinets (a few features on the walls) and the OR table."""
    x0, x1 = room.x_range_m
    # A door (a slightly different panel) and a wall of cabinets give the walls a few features.
    add("plastic", box((x1 - 0.015, -1.2, 1.05), (0.03, 1.4, 2.1)), (0.75, 0.8, 0.85))
    for i in range(4):
        add("plastic", box((x0 + 0.25, -2.4 + 0.62 * i, 1.0), (0.5, 0.6, 2.0)), (0.9, 0.9, 0.88))

    # OR table: column, top and mattress.
    add("steel", box((0.0, 0.0, 0.38), (0.35, 0.45, 0.76)))
    add("steel", box((0.0, 0.0, 0.03), (0.9, 0.6, 0.06)))
    add("steel", box((0.0, 0.0, 0.8), (2.05, 0.56, 0.08)))
    add("padding", box((0.0, 0.0, 0.88), (2.0, 0.54, 0.08)))


def _add_patient(add: _Add) -> None:
    """The draped patient on the table, and the anaesthesia screen at the neck."""
    drape_tint = (0.35, 0.55, 0.75)
    add(
        "fabric",
        ellipsoid((0.1, 0.0, TABLE_TOP_Z_M), (0.85, 0.27, 0.16), z_min_frac=0.0),
        drape_tint,
    )
    add("fabric", box((0.1, 0.0, 0.7), (1.9, 0.9, 0.02)), drape_tint)  # drape hanging down
    add(
        "skin",
        ellipsoid((-0.88, 0.0, TABLE_TOP_Z_M + 0.07), (0.11, 0.09, 0.09)),
        (0.86, 0.66, 0.55),
    )
    add(
        "fabric",
        ellipsoid((-0.88, 0.0, TABLE_TOP_Z_M + 0.13), (0.1, 0.1, 0.05)),
        (0.3, 0.5, 0.8),
    )
    # anaesthesia screen: a drape frame across the table at the patient's neck
    add("fabric", box((-0.72, 0.0, 1.3), (0.02, 0.9, 0.5)), drape_tint)


def _add_monitors(add: _Add, H: float) -> list[SceneObject]:
    """Monitors on ceiling booms, facing the table; returns their (emissive) screens."""
    screens = []
    for mx, my, yaw in ((1.7, -1.35, 2.5), (-1.5, 1.5, -0.9)):
        Rm = rot_z(yaw)
        centre = np.array([mx, my, 1.75])
        add("rubber", box(centre, (0.06, 0.62, 0.4), Rm))
        front = centre + Rm @ np.array([0.035, 0.0, 0.0])
        screens.append(
            SceneObject(
                "monitor_screen", box(front, (0.008, 0.58, 0.36), Rm), "screen", emission=1.0
            )
        )
        add("steel", cylinder(centre - Rm @ np.array([0.05, 0, 0]), (mx, my, H), 0.035))
    return screens


def _add_back_table_and_anaesthesia(add: _Add) -> list[SceneObject]:
    """The back table with an instrument tray, and an anaesthesia machine at the head end;
    returns the machine's (emissive) screen."""
    add("steel", box((-1.3, 1.95, 0.88), (1.3, 0.65, 0.03)))
    for lx in (-1.9, -0.7):
        for ly in (1.68, 2.22):
            add("steel", cylinder((lx, ly, 0.0), (lx, ly, 0.87), 0.02, segments=10))
    add("tray", box((-1.3, 1.95, 0.91), (1.2, 0.55, 0.03)))
    add("plastic", box((-2.0, -0.75, 0.75), (0.6, 0.7, 1.5)), (0.75, 0.78, 0.72))
    return [
        SceneObject(
            "anaesthesia_screen", box((-1.69, -0.75, 1.3), (0.01, 0.4, 0.3)), "screen", emission=1.0
        )
    ]


def _add_lamps(add: _Add, H: float, panels: list[tuple[float, float]]) -> list[SceneObject]:
    """The surgical light on its boom and the recessed ceiling panels (emissive objects)."""
    add("steel", cylinder((0.15, 0.0, H), (0.15, 0.0, 2.35), 0.04))
    lamps = [
        SceneObject(
            "surgical_light",
            cylinder((0.15, 0.0, 2.35), (0.15, 0.0, 2.25), 0.38, segments=32),
            "lamp",
            emission=1.6,
        )
    ]
    for px, py in panels:
        lamps.append(
            SceneObject(
                "ceiling_panel", box((px, py, H - 0.01), (1.2, 0.6, 0.01)), "lamp", emission=1.3
            )
        )
    return lamps


def _add_mobile_equipment(add: _Add) -> None:
    """The robot cart beside the table, with its arm over the patient, and the C-arm."""
    add("plastic", box((0.9, 1.15, 0.55), (0.75, 0.6, 1.1)), (0.93, 0.93, 0.95))
    add("rubber", box((0.9, 1.15, 0.05), (0.8, 0.65, 0.1)))
    add("plastic", cylinder((0.9, 1.15, 1.1), (0.9, 1.15, 1.75), 0.09), (0.9, 0.9, 0.92))
    add("plastic", cylinder((0.9, 1.15, 1.75), (0.55, 0.45, 1.55), 0.07), (0.9, 0.9, 0.92))
    add("plastic", cylinder((0.55, 0.45, 1.55), (0.35, 0.15, 1.2), 0.05), (0.9, 0.9, 0.92))
    # C-arm: base, column and the arc around the table's head end.
    add("plastic", box((-0.45, -1.65, 0.5), (0.9, 0.55, 1.0)), (0.82, 0.86, 0.9))
    add("plastic", box((-0.45, -1.25, 1.05), (0.25, 0.4, 0.25)), (0.82, 0.86, 0.9))
    add(
        "plastic",
        torus_arc((-0.45, -0.35, 1.05), 0.78, 0.07, -1.35, 1.35, R=rot_z(np.pi / 2) @ rot_x(0.0)),
        (0.82, 0.86, 0.9),
    )


def footprints(with_patient: bool, with_mobile_equipment: bool = True) -> list[Footprint]:
    """The furniture outlines for the top-down map."""
    out = [
        Footprint("OR table", (0.0, 0.0), (2.05, 0.56)),
        Footprint("back table", (-1.3, 1.95), (1.3, 0.65)),
        Footprint("anaesthesia", (-2.0, -0.75), (0.6, 0.7)),
        Footprint("cabinets", (-3.25, -1.47), (0.5, 2.48)),
        Footprint("monitor", (1.7, -1.35), (0.06, 0.62), 2.5),
        Footprint("monitor", (-1.5, 1.5), (0.06, 0.62), -0.9),
    ]
    if with_mobile_equipment:
        out.append(Footprint("robot cart", (0.9, 1.15), (0.75, 0.6)))
        out.append(Footprint("C-arm", (-0.45, -1.65), (0.9, 0.55)))
    if with_patient:
        out.append(Footprint("patient", (0.1, 0.0), (1.7, 0.5)))
    return out
