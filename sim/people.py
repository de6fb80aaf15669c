"""People who walk, turn and work along scripted paths.

A person follows a closed loop of waypoints: walk to a waypoint at walking speed, dwell there
(working or standing) facing a focus point, walk on. Everything is a pure function of time, so any
frame at any time renders the same on any machine. The body is built from simple solids (legs,
torso, arms, neck, head, cap, mask) in scrub colours; its head gives the egocentric ground truth.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from protocol.camera import Pose
from sim.geometry import Mesh, box, cylinder, ellipsoid, rot_z
from sim.room import SceneObject

WALK_SPEED_M_S = 0.9
STRIDE_M = 0.75
SKIN_TINT = (0.85, 0.64, 0.52)


@dataclass(frozen=True, kw_only=True)
class Waypoint:
    x_m: float
    y_m: float
    dwell_s: float
    focus_xyz_m: tuple[float, float, float] = (0.0, 0.0, 1.0)
    working: bool = False


@dataclass(frozen=True, kw_only=True)
class Person:
    name: str
    role: str
    scrub_tint: tuple[float, float, float]
    cap_tint: tuple[float, float, float]
    height_m: float
    waypoints: tuple[Waypoint, ...]
    start_offset_s: float = 0.0
    hand_target: object | None = None  # callable t -> (3,) world point for the right hand

    def __post_init__(self) -> None:
        if len(self.waypoints) < 1:
            raise ValueError(f"person {self.name} needs at least one waypoint")
        if not 1.4 <= self.height_m <= 2.1:
            raise ValueError(f"person {self.name}: height_m={self.height_m} is not plausible")


@dataclass(frozen=True)
class PersonState:
    name: str
    role: str
    position_xy_m: np.ndarray
    heading_rad: float
    gait_phase_rad: float
    walking_amount: float  # 0 standing .. 1 walking
    working: bool
    head_yaw_rad: float  # relative to the torso
    head_pitch_rad: float  # positive looks down
    scale: float
    t_s: float

    @property
    def head_centre_m(self) -> np.ndarray:
        return self._world(np.array([0.0, 0.0, 1.64 * self.scale]))

    def _world(self, p_local: np.ndarray) -> np.ndarray:
        x, y = self.position_xy_m
        return rot_z(self.heading_rad) @ p_local + np.array([x, y, 0.0])

    def head_rotation(self) -> np.ndarray:
        """World-from-head rotation; head axes: x forward, y left, z up."""
        c, s = np.cos(self.head_pitch_rad), np.sin(self.head_pitch_rad)
        pitch = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # +pitch tips forward-down
        return rot_z(self.heading_rad + self.head_yaw_rad) @ pitch

    def eye_pose(self) -> Pose:
        """The egocentric camera: between the eyes, looking where the head looks (OpenCV axes)."""
        Rh = self.head_rotation()
        eye = self.head_centre_m + Rh @ np.array([0.13, 0.0, 0.03]) * self.scale
        # camera axes in head coordinates: x_cam = -y_head, y_cam = -z_head, z_cam = x_head
        cam_in_head = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        R_wc = Rh @ cam_in_head.T  # world-from-camera
        R = R_wc.T
        return Pose(R=R, t_m=-R @ eye)


def _timeline(person: Person) -> tuple[np.ndarray, list[tuple[str, int]]]:
    """Segment start times and (kind, waypoint index) for one loop of the script."""
    starts, segs, t = [], [], 0.0
    wps = person.waypoints
    for i, wp in enumerate(wps):
        starts.append(t)
        segs.append(("dwell", i))
        t += wp.dwell_s
        nxt = wps[(i + 1) % len(wps)]
        dist = float(np.hypot(nxt.x_m - wp.x_m, nxt.y_m - wp.y_m))
        if dist > 1e-6:
            starts.append(t)
            segs.append(("walk", i))
            t += dist / WALK_SPEED_M_S
    starts.append(t)
    return np.asarray(starts), segs


def _raw_state(
    person: Person, t_s: float
) -> tuple[np.ndarray, float, float, float, Waypoint, bool]:
    """position, heading, gait phase, walking amount, current focus waypoint, working."""
    starts, segs = _timeline(person)
    period = starts[-1]
    tl = (t_s + person.start_offset_s) % period if period > 0 else 0.0
    k = int(np.searchsorted(starts, tl, side="right") - 1)
    k = min(max(k, 0), len(segs) - 1)
    kind, i = segs[k]
    wps = person.waypoints
    wp = wps[i]
    if kind == "dwell":
        pos = np.array([wp.x_m, wp.y_m])
        focus = np.asarray(wp.focus_xyz_m[:2]) - pos
        heading = float(np.arctan2(focus[1], focus[0])) if np.linalg.norm(focus) > 1e-6 else 0.0
        return pos, heading, 0.0, 0.0, wp, wp.working
    nxt = wps[(i + 1) % len(wps)]
    a, b = np.array([wp.x_m, wp.y_m]), np.array([nxt.x_m, nxt.y_m])
    dur = starts[k + 1] - starts[k]
    u = (tl - starts[k]) / dur
    s = u * u * (3 - 2 * u)  # ease in and out
    pos = a + (b - a) * s
    d = b - a
    dist_done = float(np.linalg.norm(d)) * s
    walking = float(np.clip(np.sin(np.pi * u) * 2.0, 0.0, 1.0))
    return pos, float(np.arctan2(d[1], d[0])), 2 * np.pi * dist_done / STRIDE_M, walking, nxt, False


def person_state(person: Person, t_s: float) -> PersonState:
    pos, _, gait, walking, focus_wp, working = _raw_state(person, t_s)
    # Smooth the heading over the last 0.6 s so turns take time instead of snapping.
    vec = np.zeros(2)
    for k, w in enumerate((0.1, 0.15, 0.2, 0.25, 0.3)):
        h = _raw_state(person, t_s - 0.15 * (4 - k))[1]
        vec += w * np.array([np.cos(h), np.sin(h)])
    heading = float(np.arctan2(vec[1], vec[0]))
    scale = person.height_m / 1.75
    head_centre = np.array([pos[0], pos[1], 1.64 * scale])
    focus = np.asarray(focus_wp.focus_xyz_m, dtype=float) - head_centre
    yaw = float(np.arctan2(focus[1], focus[0])) - heading
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    # Walking people look where they go; still people look at their focus, and glance around.
    glance = 0.25 * np.sin(0.7 * t_s + zlib.crc32(person.name.encode()) % 7)
    yaw = float(np.clip((1 - walking) * yaw + glance * (1 - walking), -1.2, 1.2))
    pitch = float(np.arctan2(-focus[2], np.hypot(focus[0], focus[1])))
    pitch = float(np.clip((1 - walking) * pitch + walking * 0.15, -0.5, 0.9))
    return PersonState(
        name=person.name,
        role=person.role,
        position_xy_m=pos,
        heading_rad=heading,
        gait_phase_rad=gait,
        walking_amount=walking,
        working=working,
        head_yaw_rad=yaw,
        head_pitch_rad=pitch,
        scale=scale,
        t_s=t_s,
    )


def person_objects(
    person: Person, state: PersonState, hand_target_m: np.ndarray | None = None
) -> list[SceneObject]:
    """The body as a few meshes (one per material), in world coordinates."""
    s = state.scale
    R = rot_z(state.heading_rad)
    T = np.array([state.position_xy_m[0], state.position_xy_m[1], 0.0])
    swing = 0.45 * state.walking_amount * np.sin(state.gait_phase_rad)

    def world(p: np.ndarray | tuple[float, ...]) -> np.ndarray:
        return R @ (np.asarray(p, dtype=float) * s) + T

    scrubs: list[Mesh] = []
    skin: list[Mesh] = []
    dark: list[Mesh] = []
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        hip = np.array([0.0, 0.1 * sgn, 0.9])
        a = swing * sgn
        foot = hip + 0.86 * np.array([np.sin(a), 0.0, -np.cos(a)])
        scrubs.append(cylinder(world(hip), world(foot + np.array([0.0, 0.0, 0.06])), 0.075 * s, 14))
        dark.append(
            box(world(foot + np.array([0.05, 0.0, 0.0])), np.array([0.26, 0.1, 0.08]) * s, R)
        )
        shoulder = np.array([0.0, 0.21 * sgn, 1.43])
        if state.working:
            wobble = 0.03 * np.sin(2.1 * state.t_s + sgn)
            elbow = shoulder + np.array([0.12, 0.03 * sgn, -0.25])
            hand = elbow + np.array([0.3 + wobble, -0.06 * sgn, -0.05 + wobble])
        else:
            elbow = shoulder + 0.3 * np.array([-np.sin(a), 0.0, -np.cos(a)])
            hand = elbow + 0.27 * np.array([-np.sin(a) + 0.25, 0.0, -np.cos(a)])
        hand_w = world(hand)
        if hand_target_m is not None and side == "right":
            # the arm reaches the target along a straight line, elbow halfway and slightly low
            hand_w = np.asarray(hand_target_m, dtype=float)
            sh_w = world(shoulder)
            elbow_w = (sh_w + hand_w) / 2 - np.array([0.0, 0.0, 0.08])
            scrubs.append(cylinder(sh_w, elbow_w, 0.055 * s, 12))
            skin.append(cylinder(elbow_w, hand_w, 0.04 * s, 12))
        else:
            scrubs.append(cylinder(world(shoulder), world(elbow), 0.055 * s, 12))
            skin.append(cylinder(world(elbow), hand_w, 0.04 * s, 12))
        skin.append(ellipsoid(hand_w, np.array([0.05, 0.04, 0.05]) * s, rings=6, segments=10))
    scrubs.append(ellipsoid(world((0.0, 0.0, 1.18)), np.array([0.14, 0.22, 0.33]) * s, R))
    skin.append(cylinder(world((0.0, 0.0, 1.45)), world((0.0, 0.0, 1.56)), 0.055 * s, 12))
    Rh = state.head_rotation()
    hc = state.head_centre_m
    skin.append(ellipsoid(hc, np.array([0.1, 0.085, 0.115]) * s, Rh, rings=12, segments=18))
    cap = ellipsoid(
        hc + Rh @ np.array([-0.01, 0.0, 0.02]) * s,
        np.array([0.108, 0.095, 0.115]) * s,
        Rh,
        rings=8,
        segments=18,
        z_min_frac=0.15,
    )
    mask = ellipsoid(
        hc + Rh @ np.array([0.06, 0.0, -0.045]) * s,
        np.array([0.05, 0.075, 0.05]) * s,
        Rh,
        rings=6,
        segments=12,
    )
    local_R = R.T
    local_t = -R.T @ T
    return [
        SceneObject(
            f"{person.name}:scrubs",
            Mesh.merge(scrubs),
            "fabric",
            person.scrub_tint,
            local_R,
            local_t,
        ),
        SceneObject(f"{person.name}:skin", Mesh.merge(skin), "skin", SKIN_TINT, local_R, local_t),
        SceneObject(f"{person.name}:cap", cap, "fabric", person.cap_tint, local_R, local_t),
        SceneObject(f"{person.name}:mask", mask, "fabric", (0.55, 0.75, 0.9), local_R, local_t),
        SceneObject(
            f"{person.name}:shoes", Mesh.merge(dark), "rubber", (1.0, 1.0, 1.0), local_R, local_t
        ),
    ]
