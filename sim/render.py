"""Ray-cast rendering of the simulated room through real lens models.

Each pixel's ray comes from inverting the sensor's OpenCV distortion, so distorted sensor images and
undistorted virtual pinholes come out of the same code. open3d's ``RaycastingScene`` (Embree) finds
the surface; shading is albedo (procedural textures in each object's own frame) times Lambertian
irradiance from the ceiling panels and the surgical light, plus emissive screens and lamps.

The wand's spheres are intersected analytically rather than as meshes, and their pixels are
supersampled, because wand calibration measures sub-pixel sphere centres: the simulated edge has to
be the edge of a true sphere, partially covering its boundary pixels as on a real sensor.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from protocol.camera import Camera, Intrinsics, undistort_to_normalized
from sim import kernels
from sim.room import Light, SceneObject
from sim.textures import Texture

AMBIENT = 0.14
SPHERE_SUPERSAMPLE = 4
SPHERE_OBJECT_BASE = 10_000  # object index of wand sphere k is SPHERE_OBJECT_BASE + k
NO_OBJECT = -1


@dataclass(frozen=True)
class Spheres:
    centres_m: np.ndarray  # (K, 3)
    radius_m: float
    albedo: tuple[float, float, float]


class FrameScene:
    """Everything in the room at one instant, ready to be ray-cast from any camera."""

    def __init__(
        self,
        objects: list[SceneObject],
        lights: list[Light],
        textures: dict[str, Texture],
        spheres: Spheres | None = None,
    ) -> None:
        self.objects = objects
        self.lights = lights
        self.textures = textures
        self.spheres = spheres
        self._raycaster = o3d.t.geometry.RaycastingScene()
        lut: list[int] = []
        for k, obj in enumerate(objects):
            if len(obj.mesh.triangles) == 0:
                continue
            gid = self._raycaster.add_triangles(
                _tensor(obj.mesh.vertices, np.float32),
                _tensor(obj.mesh.triangles, np.uint32),
            )
            while len(lut) <= gid:
                lut.append(NO_OBJECT)
            lut[gid] = k
        self._gid_to_object = np.asarray([*lut, NO_OBJECT], dtype=np.int32)
        names = list(textures)
        self.texture_stack = texture_stack(textures)
        self.texel_m = np.asarray([textures[k].texel_m for k in names], np.float32)
        self.obj_R = np.asarray([o.local_R for o in objects], np.float32).reshape(-1, 3, 3)
        self.obj_t = np.asarray([o.local_t for o in objects], np.float32).reshape(-1, 3)
        self.obj_tex = np.asarray([names.index(o.texture) for o in objects], np.int32)
        self.obj_tint = np.asarray([o.tint for o in objects], np.float32).reshape(-1, 3)
        emissive = [textures[o.texture].emissive for o in objects]
        self.obj_emission = np.asarray(
            [o.emission if em else 0.0 for o, em in zip(objects, emissive, strict=True)],
            np.float32,
        )
        self.light_pos = np.asarray([lt.position_m for lt in lights], np.float32).reshape(-1, 3)
        self.light_power = np.asarray([lt.power for lt in lights], np.float32)

    def cast_rays(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 6) float32 rays -> t (N,), object index (N,, -1 for none), normal (N, 3)."""
        out = self._raycaster.cast_rays(_tensor(rays, np.float32))
        t = out["t_hit"].numpy()
        gid = out["geometry_ids"].numpy()
        lut = self._gid_to_object
        obj = lut[np.minimum(gid, len(lut) - 1)]
        return t, obj, out["primitive_normals"].numpy()


def texture_stack(textures: dict[str, Texture]) -> np.ndarray:
    """All textures as one (T, S, S, 3) array, small ones tiled up to the common size."""
    key = id(textures)
    cached = _STACKS.get(key)
    if cached is not None and cached[0] is textures:
        return cached[1]
    size = max(t.albedo.shape[0] for t in textures.values())
    stack = np.empty((len(textures), size, size, 3), np.float32)
    for i, tex in enumerate(textures.values()):
        reps = size // tex.albedo.shape[0]
        stack[i] = np.tile(tex.albedo, (reps, reps, 1))
    _STACKS[key] = (textures, stack)
    return stack


_STACKS: dict[int, tuple[dict[str, Texture], np.ndarray]] = {}


def _tensor(array: np.ndarray, dtype: type) -> o3d.core.Tensor:
    return o3d.core.Tensor(np.ascontiguousarray(array, dtype))  # type: ignore[call-overload]


@functools.lru_cache(maxsize=24)
def ray_directions(intr: Intrinsics) -> np.ndarray:
    """(H, W, 3) float32 camera-frame ray directions with z = 1, one per pixel centre.

    For a distorted sensor these come from inverting the distortion iteratively, so projecting a
    ray back through ``cv2.projectPoints`` lands on its pixel to far below 0.01 px.
    """
    u, v = np.meshgrid(
        np.arange(intr.width_px, dtype=np.float64), np.arange(intr.height_px, dtype=np.float64)
    )
    return _directions_for_pixels(intr, np.stack([u, v], axis=-1))


def _directions_for_pixels(intr: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    shape = pixels.shape[:-1]
    xy = undistort_to_normalized(pixels.reshape(-1, 2), intr)
    d = np.ones((len(xy), 3), np.float32)
    d[:, :2] = xy
    return d.reshape(*shape, 3)


def _sample(texture: Texture, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping texture lookup at (N, 2) texel coordinates -> (N, 3)."""
    n = len(uv)
    if n == 0:
        return np.zeros((0, 3), np.float32)
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    mx = np.pad(uv[:, 0].astype(np.float32), (0, pad)).reshape(rows, cols)
    my = np.pad(uv[:, 1].astype(np.float32), (0, pad)).reshape(rows, cols)
    size = texture.albedo.shape[0]
    # remap's wrap border handles coordinates within one tile of the edge; fold the rest first
    mx = np.mod(mx, size, dtype=np.float32)
    my = np.mod(my, size, dtype=np.float32)
    out = cv2.remap(texture.albedo, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, 3)[:n]


def _irradiance(points: np.ndarray, normals: np.ndarray, lights: list[Light]) -> np.ndarray:
    e = np.full(len(points), AMBIENT, np.float32)
    for light in lights:
        to_light = light.position_m.astype(np.float32) - points
        d2 = np.einsum("ij,ij->i", to_light, to_light)
        cos = np.einsum("ij,ij->i", to_light, normals) / np.sqrt(d2)
        np.maximum(cos, 0.0, out=cos)
        e += light.power * cos / np.maximum(d2, 0.25)
    return e


def shade_reference(
    scene: FrameScene, points: np.ndarray, normals: np.ndarray, objects: np.ndarray
) -> np.ndarray:
    """Linear radiance (N, 3) for hit points of known object index; ``normals`` face the viewer.

    The slow, obvious twin of ``sim.kernels.shade_pixels``; the tests hold the two together.
    """
    radiance = np.zeros((len(points), 3), np.float32)
    order = np.argsort(objects, kind="stable")
    sorted_obj = objects[order]
    bounds = np.searchsorted(sorted_obj, np.arange(len(scene.objects) + 1))
    by_texture: dict[str, list[tuple[np.ndarray, np.ndarray, SceneObject]]] = {}
    for k, obj in enumerate(scene.objects):
        idx = order[bounds[k] : bounds[k + 1]]
        if len(idx) == 0:
            continue
        p_local = points[idx] @ obj.local_R.T.astype(np.float32) + obj.local_t.astype(np.float32)
        n_local = np.abs(normals[idx] @ obj.local_R.T.astype(np.float32))
        axis = np.argmax(n_local, axis=1)
        u = np.where(axis == 0, p_local[:, 1], p_local[:, 0])
        v = np.where(axis == 2, p_local[:, 1], p_local[:, 2])
        tex = scene.textures[obj.texture]
        uv = np.stack([u, v], axis=1) / tex.texel_m
        by_texture.setdefault(obj.texture, []).append((idx, uv, obj))
    for name, groups in by_texture.items():
        tex = scene.textures[name]
        all_idx = np.concatenate([g[0] for g in groups])
        albedo = _sample(tex, np.concatenate([g[1] for g in groups]))
        tint = np.concatenate(
            [np.broadcast_to(np.asarray(g[2].tint, np.float32), (len(g[0]), 3)) for g in groups]
        )
        albedo *= tint
        if tex.emissive:
            scale = np.concatenate([np.full(len(g[0]), g[2].emission, np.float32) for g in groups])
            radiance[all_idx] = albedo * scale[:, None]
        else:
            e = _irradiance(points[all_idx], normals[all_idx], scene.lights)
            radiance[all_idx] = albedo * e[:, None]
    return radiance


@dataclass(frozen=True)
class RayImage:
    radiance: np.ndarray  # (H, W, 3) float32, linear
    depth_m: np.ndarray  # (H, W) float32, z in the camera frame; inf where nothing was hit
    object_index: np.ndarray  # (H, W) int32; SPHERE_OBJECT_BASE + k for wand sphere k


def render_view(
    scene: FrameScene,
    camera: Camera,
    background: RayImage | None = None,
    region: np.ndarray | None = None,
) -> RayImage:
    """Render ``camera``'s view of ``scene``.

    With ``background`` (a render of the static room from the same camera) and ``region`` (flat
    pixel indices that every moving object's projection falls in), only the region is ray-cast
    and the rest is copied from the background. Lighting casts no shadows, so moving objects
    change no pixel outside their own projection and the result is identical to a full render.
    """
    intr = camera.intrinsics
    H, W = intr.height_px, intr.width_px
    dirs_cam = ray_directions(intr).reshape(-1, 3)
    if region is not None:
        dirs_cam = np.ascontiguousarray(dirs_cam[region])
    R = camera.pose.R.astype(np.float32)
    origin = camera.pose.centre_m.astype(np.float32)
    rays = kernels.make_rays(dirs_cam, R, origin)
    t, objects, normals = scene.cast_rays(rays)
    radiance = kernels.shade_pixels(
        rays,
        t,
        objects,
        normals,
        scene.obj_R,
        scene.obj_t,
        scene.obj_tex,
        scene.obj_tint,
        scene.obj_emission,
        scene.texture_stack,
        scene.texel_m,
        scene.light_pos,
        scene.light_power,
        AMBIENT,
    )
    if region is not None and background is not None:
        full_rad = background.radiance.reshape(-1, 3).copy()
        full_t = background.depth_m.reshape(-1).copy()
        full_obj = background.object_index.reshape(-1).copy()
        full_rad[region] = radiance
        full_t[region] = t
        full_obj[region] = objects
        radiance, t, objects = full_rad, full_t, full_obj
    radiance = radiance.reshape(H, W, 3)
    depth = t.reshape(H, W)  # ray z = 1 in the camera frame, so t is depth; misses are inf
    objects = objects.reshape(H, W)
    if scene.spheres is not None:
        _composite_spheres(scene, camera, radiance, depth, objects)
    return RayImage(radiance, depth, objects)


def moving_region(camera: Camera, meshes: list, margin_px: int = 3) -> np.ndarray | None:
    """Flat indices of the pixels that the given meshes can cover, as a union of the
    projected bounding boxes of their vertices (plus a margin for the lens' curvature of
    straight edges); None when a mesh reaches behind or beside the camera (render everything)."""
    intr = camera.intrinsics
    H, W = intr.height_px, intr.width_px
    mask = np.zeros((H, W), bool)
    for mesh in meshes:
        v = mesh.vertices.astype(np.float64)
        if len(v) == 0:
            continue
        z = v @ camera.pose.R[2] + camera.pose.t_m[2]
        if z.min() < 0.05:
            if z.max() < 0.05:
                continue  # wholly behind the camera
            return None
        px, _ = camera.project(v)
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - margin_px
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + margin_px
        if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
            continue
        # a wide lens maps points far outside the view to odd places: be safe, render it all
        if u0 < -W or v0 < -H or u1 > 2 * W or v1 > 2 * H:
            return None
        mask[max(v0, 0) : min(v1, H - 1) + 1, max(u0, 0) : min(u1, W - 1) + 1] = True
    return np.flatnonzero(mask)


def _composite_spheres(
    scene: FrameScene, camera: Camera, radiance: np.ndarray, depth: np.ndarray, objects: np.ndarray
) -> None:
    spheres = scene.spheres
    assert spheres is not None
    intr = camera.intrinsics
    H, W = depth.shape
    r = spheres.radius_m
    origin = camera.pose.centre_m
    R = camera.pose.R
    ss = SPHERE_SUPERSAMPLE
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    for k, c in enumerate(spheres.centres_m):
        c_cam = R @ c + camera.pose.t_m
        dist = float(np.linalg.norm(c_cam))
        if c_cam[2] <= r or dist <= r * 1.01:
            continue
        # bounding box from projecting points around the silhouette cone, with a margin
        ring = _silhouette_points(c_cam, r)
        px, _ = camera.project((ring - camera.pose.t_m) @ R)  # camera->world for project()
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - 2
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + 2
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, W - 1), min(v1, H - 1)
        if u1 < u0 or v1 < v0:
            continue
        uu, vv = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
        sub_u = uu[..., None, None] + offsets[None, None, None, :]
        sub_v = vv[..., None, None] + offsets[None, None, :, None]
        sub = np.stack(np.broadcast_arrays(sub_u, sub_v), axis=-1)  # (h, w, ss, ss, 2)
        d_cam = _directions_for_pixels(intr, sub).astype(np.float64)  # z = 1
        d_world = d_cam @ R
        oc = origin - c
        a = np.einsum("...i,...i->...", d_world, d_world)
        b = 2 * np.einsum("...i,i->...", d_world, oc)
        cc = float(oc @ oc - r * r)
        disc = b * b - 4 * a * cc
        hit = disc >= 0
        s = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)  # = depth (z=1)
        bg_depth = depth[v0 : v1 + 1, u0 : u1 + 1][..., None, None]
        hit &= (s > 0) & (s < bg_depth)
        if not hit.any():
            continue
        p = origin + d_world * np.where(hit, s, 0)[..., None]
        n = (p - c) / r
        e = _irradiance(p[hit].astype(np.float32), n[hit].astype(np.float32), scene.lights)
        sub_rad = np.zeros((*hit.shape, 3), np.float32)
        sub_rad[hit] = np.asarray(spheres.albedo, np.float32) * e[:, None]
        cover = hit.mean(axis=(2, 3))
        sphere_mean = sub_rad.sum(axis=(2, 3)) / np.maximum(hit.sum(axis=(2, 3)), 1)[..., None]
        patch = radiance[v0 : v1 + 1, u0 : u1 + 1]
        patch[:] = cover[..., None] * sphere_mean + (1 - cover[..., None]) * patch
        centre_hit = hit[:, :, ss // 2, ss // 2]
        centre_s = s[:, :, ss // 2, ss // 2]
        dpatch = depth[v0 : v1 + 1, u0 : u1 + 1]
        dpatch[centre_hit] = centre_s[centre_hit]
        opatch = objects[v0 : v1 + 1, u0 : u1 + 1]
        opatch[cover >= 0.5] = SPHERE_OBJECT_BASE + k


def _silhouette_points(c_cam: np.ndarray, r: float, n: int = 24) -> np.ndarray:
    """Points (camera frame) on the sphere's silhouette circle, pushed out slightly."""
    d = np.linalg.norm(c_cam)
    axis = c_cam / d
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(axis, helper)
    x /= np.linalg.norm(x)
    y = np.cross(axis, x)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rr = r * 1.3
    return c_cam + rr * (np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y)
