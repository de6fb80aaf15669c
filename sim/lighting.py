"""The room's light model, shared by the mesh shader and the wand's spheres: an ambient term plus
Lambertian irradiance from point lights (the ceiling panels and the surgical light), no shadows."""

from __future__ import annotations

import numpy as np

from sim.room import Light

AMBIENT = 0.14


def irradiance(points: np.ndarray, normals: np.ndarray, lights: list[Light]) -> np.ndarray:
    """(N,) float32 irradiance at (N, 3) float32 points with unit normals facing the viewer."""
    e = np.full(len(points), AMBIENT, np.float32)
    for light in lights:
        to_light = light.position_m.astype(np.float32) - points
        d2 = np.einsum("ij,ij->i", to_light, to_light)
        cos = np.einsum("ij,ij->i", to_light, normals) / np.sqrt(d2)
        np.maximum(cos, 0.0, out=cos)
        e += light.power * cos / np.maximum(d2, 0.25)
    return e
