"""Each track's head pose over time: where the eye is and where it looks.

Facing (yaw): a walking person faces where they go; a standing one faces across their shoulder
line, on the side their arms reach out to (work is done in front), where the room's raised
surface is (the table) when it is on one side only, and where the others standing near them are
(a team faces into the space it shares: ``group_sides``). The evidence of each
timestamp is one vector, the reach difference along the shoulder normal plus the motion, summed
over ``facing_smooth_s`` so that one unclear timestamp takes its neighbours' side. Pitch: a
walker looks ``default_pitch_deg`` down; a standing person looks at the middle of the raised
surface in front of them (the detection's gaze for the chosen side). The eye sits
``eye_forward_m`` in front of and ``eye_up_m`` above the head's centre, which lies
``crown_to_centre_m`` below the top of the head.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reconstructor.people.config import PeopleConfig
from reconstructor.people.track import Track

SURFACE_NEAR_M = 1.0  # a surface this close on one side only says which side is the front ...
SURFACE_WEIGHT_M = 0.25  # ... as strongly as arms reaching 25 cm further out on that side


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
    (0: nobody near). ``heads_at``: every track's head (x, y) at each time.

    A team at work stands round what it works on, each facing into the space they share (the
    F-formation of a group): the middle of the others is in front of a person, not behind."""
    out = np.zeros(len(track.detections))
    for i, (t, d) in enumerate(zip(track.times_s, track.detections, strict=True)):
        own = np.asarray(d.head_xy_m)
        others = heads_at.get(round(t, 6), np.zeros((0, 2)))
        dist = np.hypot(*(others - own).T) if len(others) else np.zeros(0)
        near = others[(dist > config.min_head_separation_m) & (dist <= config.group_radius_m)]
        if len(near):
            normal = np.array([math.cos(d.normal_rad(0)), math.sin(d.normal_rad(0))])
            out[i] = float(np.sign(normal @ (near.mean(axis=0) - own)))
    return out


def head_poses(
    track: Track, config: PeopleConfig, group_side: np.ndarray | None = None
) -> list[HeadPose]:
    """``group_side``: ``group_sides`` of the track (none: no group evidence)."""
    times = np.asarray(track.times_s)
    dets = track.detections
    xy = track.xy()
    vel = _velocities(times, xy, 2 * config.facing_smooth_s)
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
    walking = speed > config.walking_speed_m_s
    evidence[walking] += vel[walking] / speed[walking, None] * 0.3
    out = []
    for i, t in enumerate(times):
        near = np.abs(times - t) <= config.facing_smooth_s / 2
        vote = evidence[near].sum(axis=0)
        d = dets[i]
        if walking[i]:
            yaw = math.atan2(vel[i, 1], vel[i, 0])
            pitch = math.radians(config.default_pitch_deg)
        else:
            side = 0 if float(normals[i] @ vote) >= 0 else 1
            yaw = d.normal_rad(side)
            pitch = d.gaze_pitch_rad[side]
        centre = np.array([*d.head_xy_m, d.top_m - config.crown_to_centre_m])
        cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
        forward = np.array([cy * cp, sy * cp, -sp])
        up = np.array([cy * sp, sy * sp, cp])
        eye = centre + config.eye_forward_m * forward + config.eye_up_m * up
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        out.append(HeadPose(float(t), eye, yaw, float(pitch), d.confidence))
    return out
