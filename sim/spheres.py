"""The wand's spheres: intersected analytically, not as meshes, and supersampled, because wand
calibration measures sub-pixel sphere centres: the simulated edge has to be the edge of a true
sphere, partially covering its boundary pixels as on a real sensor.

``composite_spheres`` supersamples only the pixels whose footprint can reach a sphere's disc
(a cone test on the cached pixel-centre rays, with a pixel's angular size as margin);
``composite_spheres_reference`` is its obvious twin that supersamples every pixel of the
sphere's bounding box. Pixels that no sample of a sphere reaches are left exactly as they were
by both, so the two give the same image (the tests hold them equal).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.camera import Camera
from sim.geometry import unit_circle
from sim.lighting import irradiance
from sim.rays import directions_for_pixels, ray_directions
from sim.room import Light

SPHERE_SUPERSAMPLE = 4
SPHERE_OBJECT_BASE = 10_000  # object index of wand sphere k is SPHERE_OBJECT_BASE + k


@dataclass(frozen=True)
class Spheres:
    centres_m: np.ndarray  # (K, 3)
    radius_m: float
    albedo: tuple[float, float, float]


def composite_spheres(
    spheres: Spheres,
    lights: list[Light],
    camera: Camera,
    radiance: np.ndarray,
    depth: np.ndarray,
    objects: np.ndarray,
) -> None:
    """Draw the spheres into ``camera``'s image (in place), nearer than ``depth`` only."""
    centre_rays = ray_directions(camera.intrinsics)
    for k, box in _boxes(spheres, camera, depth.shape):
        u0, v0, u1, v1 = box
        c_cam = camera.pose.R @ spheres.centres_m[k] + camera.pose.t_m
        d = centre_rays[v0 : v1 + 1, u0 : u1 + 1].astype(np.float64)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        # a pixel's samples lie within half a pixel of its centre ray: keep the pixels whose
        # centre ray is within the sphere's angular radius plus one pixel's angular size
        pitch = _max_angle(d[:, 1:], d[:, :-1]) + _max_angle(d[1:], d[:-1])
        dist = float(np.linalg.norm(c_cam))
        cos = np.clip(d @ (c_cam / dist), -1.0, 1.0)
        near = np.arccos(cos) <= np.arcsin(spheres.radius_m / dist) + pitch + 1e-9
        vv, uu = np.nonzero(near)
        if len(vv) == 0:
            continue
        _shade_sphere(spheres, k, lights, camera, radiance, depth, objects, vv + v0, uu + u0)


def composite_spheres_reference(
    spheres: Spheres,
    lights: list[Light],
    camera: Camera,
    radiance: np.ndarray,
    depth: np.ndarray,
    objects: np.ndarray,
) -> None:
    """The slow, obvious twin of ``composite_spheres``: every pixel of each box supersampled."""
    for k, (u0, v0, u1, v1) in _boxes(spheres, camera, depth.shape):
        vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
        _shade_sphere(spheres, k, lights, camera, radiance, depth, objects, vv.ravel(), uu.ravel())


def _max_angle(a: np.ndarray, b: np.ndarray) -> float:
    if a.size == 0:
        return 0.0
    cos = np.clip(np.einsum("...i,...i->...", a, b), -1.0, 1.0)
    return float(np.arccos(cos).max())


def _boxes(spheres: Spheres, camera: Camera, shape: tuple[int, ...]):
    """(sphere index, (u0, v0, u1, v1)) of each sphere in front of the camera and in view: the
    projection of points around its silhouette cone, with a margin."""
    H, W = shape[:2]
    r = spheres.radius_m
    R = camera.pose.R
    for k, c in enumerate(spheres.centres_m):
        c_cam = R @ c + camera.pose.t_m
        dist = float(np.linalg.norm(c_cam))
        if c_cam[2] <= r or dist <= r * 1.01:
            continue
        ring = _silhouette_points(c_cam, r)
        px, _ = camera.project((ring - camera.pose.t_m) @ R)  # camera->world for project()
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - 2
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + 2
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, W - 1), min(v1, H - 1)
        if u1 < u0 or v1 < v0:
            continue
        yield k, (int(u0), int(v0), int(u1), int(v1))


def _shade_sphere(
    spheres: Spheres,
    k: int,
    lights: list[Light],
    camera: Camera,
    radiance: np.ndarray,
    depth: np.ndarray,
    objects: np.ndarray,
    vv: np.ndarray,
    uu: np.ndarray,
) -> None:
    """Supersample sphere ``k`` over the pixels (vv, uu) and blend it over what is there."""
    ss = SPHERE_SUPERSAMPLE
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    c = spheres.centres_m[k]
    r = spheres.radius_m
    origin = camera.pose.centre_m
    sub_u = uu[:, None, None] + offsets[None, None, :]
    sub_v = vv[:, None, None] + offsets[None, :, None]
    sub = np.stack(np.broadcast_arrays(sub_u, sub_v), axis=-1)  # (n, ss, ss, 2)
    d_cam = directions_for_pixels(camera.intrinsics, sub).astype(np.float64)  # z = 1
    d_world = d_cam @ camera.pose.R
    oc = origin - c
    a = np.einsum("...i,...i->...", d_world, d_world)
    b = 2 * np.einsum("...i,i->...", d_world, oc)
    cc = float(oc @ oc - r * r)
    disc = b * b - 4 * a * cc
    hit = disc >= 0
    s = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)  # = depth (z=1)
    hit &= (s > 0) & (s < depth[vv, uu][:, None, None])
    if not hit.any():
        return
    p = origin + d_world * np.where(hit, s, 0)[..., None]
    n = (p - c) / r
    e = irradiance(p[hit].astype(np.float32), n[hit].astype(np.float32), lights)
    sub_rad = np.zeros((*hit.shape, 3), np.float32)
    sub_rad[hit] = np.asarray(spheres.albedo, np.float32) * e[:, None]
    cover = hit.mean(axis=(1, 2))
    sphere_mean = sub_rad.sum(axis=(1, 2)) / np.maximum(hit.sum(axis=(1, 2)), 1)[..., None]
    radiance[vv, uu] = cover[..., None] * sphere_mean + (1 - cover[..., None]) * radiance[vv, uu]
    centre_hit = hit[:, ss // 2, ss // 2]
    depth[vv[centre_hit], uu[centre_hit]] = s[:, ss // 2, ss // 2][centre_hit]
    covered = cover >= 0.5
    objects[vv[covered], uu[covered]] = SPHERE_OBJECT_BASE + k


def _silhouette_points(c_cam: np.ndarray, r: float, n: int = 24) -> np.ndarray:
    """Points (camera frame) on the sphere's silhouette circle, pushed out slightly."""
    # the circle negated starts half a turn round: the points (and their order) this function
    # has always drawn, bit for bit, so the pixel boxes do not move
    return c_cam - r * 1.3 * unit_circle(c_cam / np.linalg.norm(c_cam), n)
