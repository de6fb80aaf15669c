"""Each track's head pose over time: where the eye is and where it looks.

Facing (yaw): a walking person faces where they go; a standing one faces across their shoulder
line, on the side their arms reach out to (work is done in front), where the room's raised
surface is (the table) when it is on one side only, and where the others standing near them are
(a team faces into the space it shares: ``group_sides``). The evidence of each
timestamp is one vector, the reach difference along the shoulder normal plus the motion, summed
over ``facing_smooth_s`` so that one unclear timestamp takes its neighbours' side. Pitch: a
walker looks ``default_pitch_deg`` down; a standing person looks at the middle of the raised
surface in front of them (the detection's gaze for the chosen side), or, with none seen there
(hidden under their arms or a neighbour's), at their hands: ``work_height_m`` high,
``work_reach_m`` in front of the head. The eye sits
``eye_forward_m`` in front of and ``eye_up_m`` above the head's centre, which lies
``crown_to_centre_m`` below the top of the head.

A team standing round what it works on (an F-formation: Kendon 1990; Cristani et al., "Social
interaction discovery by statistical analysis of F-formations", BMVC 2011) faces one shared
point, its o-space, where the lines across their shoulders meet (``ospace_points``). Each
person's shoulder line is a few tens of degrees off (arms and neighbours fall in its band), but
the point nearest all of a group's lines, over a few seconds, is steadier than any one of them:
a member who faces towards it (the side already chosen) looks at it, down to work height.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from dataclasses import dataclass

import numpy as np

from reconstructor.people.config import PeopleConfig
from reconstructor.people.track import Track

SURFACE_NEAR_M = 1.0  # a surface this close on one side only says which side is the front ...
SURFACE_WEIGHT_M = 0.25  # ... as strongly as arms reaching 25 cm further out on that side
OSPACE_SCALE_M = 0.3  # a shoulder line this far from the shared point counts half (Cauchy)
OSPACE_MIN_M = 0.3  # the shared point lies in front of the head, not in it


@dataclass(frozen=True)
class HeadPose:
    time_s: float
    eye_m: np.ndarray  # (3,)
    yaw_rad: float  # from +x towards +y
    pitch_rad: float  # positive looks down
    confidence: float

    def gaze(self) -> np.ndarray:
        c = math.cos(self.pitch_rad)
        return np.array(
            [c * math.cos(self.yaw_rad), c * math.sin(self.yaw_rad), -math.sin(self.pitch_rad)]
        )


def _velocities(times: np.ndarray, xy: np.ndarray, window_s: float) -> np.ndarray:
    """(N, 2) m/s: the displacement across +-``window_s``/2 around each time."""
    out = np.zeros_like(xy)
    for i, t in enumerate(times):
        lo = int(np.searchsorted(times, t - window_s / 2))
        hi = int(np.searchsorted(times, t + window_s / 2, side="right")) - 1
        if hi > lo:
            out[i] = (xy[hi] - xy[lo]) / (times[hi] - times[lo])
    return out


def group_sides(
    track: Track, heads_at: dict[float, np.ndarray], config: PeopleConfig
) -> np.ndarray:
    """(N,) +1 / -1 / 0 for each of ``track``'s detections: on which side of its shoulder line
    (+normal, -normal) the other people standing within ``group_radius_m`` are, on average
    (0: fewer than ``group_min_people`` - 1 others near). ``heads_at``: every track's head (x, y)
    at each time.

    A team at work stands round what it works on, each facing into the space they share (the
    F-formation of a group): the middle of the others is in front of a person, not behind. Two
    people alone say nothing of it: a pair works side by side or back to back (two cleaners
    wiping down a room) as often as face to face."""
    out = np.zeros(len(track.detections))
    for i, (t, d) in enumerate(zip(track.times_s, track.detections, strict=True)):
        own = np.asarray(d.head_xy_m)
        others = heads_at.get(round(t, 6), np.zeros((0, 2)))
        dist = np.hypot(*(others - own).T) if len(others) else np.zeros(0)
        near = others[(dist > config.min_head_separation_m) & (dist <= config.group_radius_m)]
        if len(near) and len(near) + 1 >= config.group_min_people:
            normal = np.array([math.cos(d.normal_rad(0)), math.sin(d.normal_rad(0))])
            out[i] = float(np.sign(normal @ (near.mean(axis=0) - own)))
    return out


def _standing(track: Track, config: PeopleConfig) -> tuple[np.ndarray, np.ndarray]:
    """(velocities (N, 2) m/s, walking (N,) bool) of a track's detections."""
    vel = _velocities(np.asarray(track.times_s), track.xy(), 2 * config.facing_smooth_s)
    return vel, np.linalg.norm(vel, axis=1) > config.walking_speed_m_s


def _nearest_point(heads: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
    """The point nearest the lines through ``heads`` along ``normals`` ((L, 2) each), lines
    far from it down-weighted (iteratively reweighted least squares, Cauchy weights); None where
    the lines are near parallel (no one point is nearest)."""
    across = np.stack([-normals[:, 1], normals[:, 0]], axis=1)
    offset = np.sum(across * heads, axis=1)
    weight = np.ones(len(heads))
    point = None
    for _ in range(10):
        a = np.einsum("l,li,lj->ij", weight, across, across)
        if np.linalg.eigvalsh(a / weight.sum())[0] < 0.05:  # e.g. two lines under 26 deg apart
            return None
        point = np.linalg.solve(a, (weight * offset) @ across)
        weight = 1 / (1 + ((across @ point - offset) / OSPACE_SCALE_M) ** 2)
    return point


def _groups(heads: np.ndarray, radius_m: float) -> list[list[int]]:
    """Indices of ``heads`` joined where two stand within ``radius_m`` (single linkage)."""
    label = list(range(len(heads)))

    def root(i: int) -> int:
        while label[i] != i:
            i = label[i]
        return i

    for i in range(len(heads)):
        for j in range(i + 1, len(heads)):
            if np.hypot(*(heads[i] - heads[j])) <= radius_m:
                label[root(i)] = root(j)
    out: dict[int, list[int]] = {}
    for i in range(len(heads)):
        out.setdefault(root(i), []).append(i)
    return list(out.values())


def ospace_points(tracks: list[Track], config: PeopleConfig) -> dict[int, np.ndarray]:
    """{track id: (N, 2)}: for each detection of each track, the o-space point of the group it
    stands in (NaN: none).

    At each timestamp the people standing (not walking) within ``group_radius_m`` of one another
    are a group; the point nearest their shoulder lines' normals over ``ospace_window_s`` around
    it is the group's shared point if it lies within ``ospace_angle_deg`` of a member's normal
    line and ``ospace_reach_m`` of their head; members it does not fit are left out and the
    point found again. A group of fewer than ``ospace_min_people`` fitting members has none."""
    lines: dict[float, list[tuple[int, int, np.ndarray, np.ndarray]]] = {}
    for tr in tracks:
        _, walking = _standing(tr, config)
        for k, (t, d) in enumerate(zip(tr.times_s, tr.detections, strict=True)):
            if not walking[k]:
                normal = np.array([math.cos(d.normal_rad(0)), math.sin(d.normal_rad(0))])
                lines.setdefault(round(t, 6), []).append(
                    (tr.id, k, np.asarray(d.head_xy_m), normal)
                )
    times = sorted(lines)
    out = {tr.id: np.full((len(tr.detections), 2), np.nan) for tr in tracks}
    cos_max = math.cos(math.radians(config.ospace_angle_deg))
    for t in times:
        now = lines[t]
        lo = bisect_left(times, t - config.ospace_window_s / 2 - 1e-6)
        hi = bisect_right(times, t + config.ospace_window_s / 2 + 1e-6)
        pooled = [line for tt in times[lo:hi] for line in lines[tt]]
        for group in _groups(np.array([line[2] for line in now]), config.group_radius_m):
            members = {now[i][0] for i in group}
            point = None
            for _ in range(5):
                if len(members) < config.ospace_min_people:
                    point = None
                    break
                use = [line for line in pooled if line[0] in members]
                point = _nearest_point(np.array([u[2] for u in use]), np.array([u[3] for u in use]))
                if point is None:
                    break
                fit = set()
                for i in group:
                    tid, _, head, normal = now[i]
                    dist = float(np.hypot(*(point - head)))
                    if OSPACE_MIN_M <= dist <= config.ospace_reach_m:
                        if abs(float(normal @ (point - head))) >= cos_max * dist:
                            fit.add(tid)
                if fit == members:
                    break
                members = fit
            if point is not None and len(members) >= config.ospace_min_people:
                for i in group:
                    if now[i][0] in members:
                        out[now[i][0]][now[i][1]] = point
    return out


def head_poses(
    track: Track,
    config: PeopleConfig,
    group_side: np.ndarray | None = None,
    ospace: np.ndarray | None = None,
) -> list[HeadPose]:
    """``group_side``: ``group_sides`` of the track (none: no group evidence); ``ospace``: its
    ``ospace_points`` (none: no shared points)."""
    times = np.asarray(track.times_s)
    dets = track.detections
    vel, walking = _standing(track, config)
    speed = np.linalg.norm(vel, axis=1)
    normals = np.array([[math.cos(d.normal_rad(0)), math.sin(d.normal_rad(0))] for d in dets])
    reach = np.array([d.reach_m[0] - d.reach_m[1] for d in dets])
    # a standing person faces the raised surface (the table) on one side rather than none
    near_surface = np.array(
        [float(d.surface_m[0] <= SURFACE_NEAR_M) - float(d.surface_m[1] <= SURFACE_NEAR_M)
         for d in dets]
    )  # fmt: skip
    group = np.zeros(len(dets)) if group_side is None else np.asarray(group_side, np.float64)
    evidence = (
        normals * (reach + SURFACE_WEIGHT_M * near_surface + config.group_weight_m * group)[:, None]
    )
    evidence[walking] += vel[walking] / speed[walking, None] * 0.3
    shared = np.full((len(dets), 2), np.nan) if ospace is None else np.asarray(ospace)
    out = []
    for i, t in enumerate(times):
        near = np.abs(times - t) <= config.facing_smooth_s / 2
        vote = evidence[near].sum(axis=0)
        d = dets[i]
        centre = np.array([*d.head_xy_m, d.top_m - config.crown_to_centre_m])
        if walking[i]:
            yaw = math.atan2(vel[i, 1], vel[i, 0])
            pitch = math.radians(config.default_pitch_deg)
        else:
            side = 0 if float(normals[i] @ vote) >= 0 else 1
            yaw = d.normal_rad(side)
            pitch = d.gaze_pitch_rad[side]
            if not math.isfinite(d.surface_m[side]):
                pitch = math.atan2(centre[2] - config.work_height_m, config.work_reach_m)
            to_shared = shared[i] - centre[:2]
            if np.isfinite(to_shared).all() and float(to_shared @ normals[i]) * (1 - 2 * side) > 0:
                yaw = math.atan2(to_shared[1], to_shared[0])
                pitch = math.atan2(centre[2] - config.work_height_m, float(np.hypot(*to_shared)))
        cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
        forward = np.array([cy * cp, sy * cp, -sp])
        up = np.array([cy * sp, sy * sp, cp])
        eye = centre + config.eye_forward_m * forward + config.eye_up_m * up
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        out.append(HeadPose(float(t), eye, yaw, float(pitch), d.confidence))
    return out
