"""The wand's motion: it lies on the floor first (so calibration can find the floor plane), is
picked up, then waved along a smooth random path through the capture volume. The path is a sum of
sinusoids with seeded frequencies and phases: smooth, deterministic, and defined at any time."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from protocol.camera import Camera
from protocol.formats.wand import WandSpec
from sim.wand_tour import Tour, coverage_tour

HANDLE_M = 0.25  # rod beyond the first sphere, where the operator holds it
ROD_RADIUS_M = 0.006


@dataclass(frozen=True, kw_only=True)
class WandMotion:
    spec: WandSpec
    seed: int
    floor_lie_s: float = 2.0
    pickup_s: float = 1.5
    # the open space over the table, clear of the table top, the monitors and the surgical light:
    # the volume the rig must reconstruct, seen by all four cameras at 2.5-4.5 m
    centre_m: tuple[float, float, float] = (0.0, 0.0, 1.45)
    half_extent_m: tuple[float, float, float] = (1.3, 1.0, 0.4)
    # the rig's (left) cameras: when given, the operator takes the wand through every camera's
    # view (sim/wand_tour.py) instead of only over the table, as the calibration report asks
    cameras: tuple[Camera, ...] = ()
    half_room_m: tuple[float, float] = (3.5, 3.0)

    @functools.cached_property
    def tour(self) -> Tour | None:
        if not self.cameras:
            return None
        return coverage_tour(self.cameras, self.half_room_m, np.asarray(self.centre_m))

    def _params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng = np.random.default_rng([self.seed, 0xA4D])
        freqs = rng.uniform(0.04, 0.16, size=(5, 3)) * 2 * np.pi  # slow sweeps through the room
        phases = rng.uniform(0, 2 * np.pi, size=(5, 3))
        weights = rng.uniform(0.5, 1.0, size=(5, 3))
        return freqs, phases, weights

    def _free_pose(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Middle-sphere centre and unit rod direction while waved."""
        freqs, phases, weights = self._params()
        w = weights / weights.sum(axis=0)
        wave = (w * np.sin(freqs * t_s + phases)).sum(axis=0)
        if self.tour is None:
            centre = np.asarray(self.centre_m) + np.asarray(self.half_extent_m) * np.clip(
                wave * 1.6, -1, 1
            )
        else:  # the tour, with the seeded wave as a small hand tremor around it
            centre = self.tour.position(t_s - self.floor_lie_s) + 0.06 * wave
        yaw = 0.9 * t_s + phases[0, 0]
        pitch = 0.9 * np.sin(0.53 * t_s + phases[1, 1])  # mostly horizontal, sometimes steep
        direction = np.array(
            [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)]
        )
        return centre, direction

    def _floor_pose(self) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng([self.seed, 0xF100])
        yaw = rng.uniform(0, np.pi)
        direction = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        centre = np.array([rng.uniform(0.8, 1.6), rng.uniform(-1.2, -0.6), self.spec.radius_m])
        return centre, direction

    def pose(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(position of the first sphere's centre, unit direction towards the last sphere)."""
        c0, d0 = self._floor_pose()
        mid_offset = self.spec.sphere_positions_mm[1] / 1000.0
        if t_s <= self.floor_lie_s:
            centre, direction = c0, d0
        else:
            c1, d1 = self._free_pose(t_s)
            u = min(1.0, (t_s - self.floor_lie_s) / self.pickup_s)
            s = u * u * (3 - 2 * u)
            centre = (1 - s) * c0 + s * c1
            direction = (1 - s) * d0 + s * d1
            direction /= np.linalg.norm(direction)
        return centre - mid_offset * direction, direction

    def sphere_centres(self, t_s: float) -> np.ndarray:
        """(3, 3) world positions of the three sphere centres, in the order of the spec."""
        first, direction = self.pose(t_s)
        offsets = np.asarray(self.spec.sphere_positions_mm) / 1000.0
        return first[None, :] + offsets[:, None] * direction[None, :]

    def on_floor(self, t_s: float) -> bool:
        return t_s <= self.floor_lie_s

    def handle_end(self, t_s: float) -> np.ndarray:
        first, direction = self.pose(t_s)
        return first - HANDLE_M * direction
