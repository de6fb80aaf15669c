"""Ray-cast rendering of the simulated room through real lens models.

Each pixel's ray comes from inverting the sensor's OpenCV distortion, so distorted sensor images and
undistorted virtual pinholes come out of the same code. open3d's ``RaycastingScene`` (Embree) finds
the surface; shading is albedo (procedural textures in each object's own frame) times Lambertian
irradiance from the ceiling panels and the surgical light, plus emissive screens and lamps.

The wand's spheres are intersected analytically and supersampled (``sim.spheres``). A fixed
camera renders the static room once and then only the moving objects over it
(``render_over_background``), which gives the same image at a fraction of the cost.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from protocol.camera import Camera, Intrinsics
from sim import kernels
from sim.lighting import AMBIENT, irradiance
from sim.rays import ray_directions
from sim.room import Light, SceneObject
from sim.spheres import (
    SPHERE_OBJECT_BASE,
    SPHERE_SUPERSAMPLE,
    Spheres,
    composite_spheres,
)
from sim.textures import Texture

__all__ = [
    "AMBIENT",
    "SPHERE_OBJECT_BASE",
    "SPHERE_SUPERSAMPLE",
    "FrameScene",
    "RayImage",
    "Spheres",
    "moving_region",
    "ray_directions",
    "render_over_background",
    "render_view",
    "shade_reference",
]
NO_OBJECT = -1


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

    def shade(
        self, rays: np.ndarray, t_hit: np.ndarray, objects: np.ndarray, normals: np.ndarray
    ) -> np.ndarray:
        """(N, 3) float32 radiance where ``rays`` hit this scene (``cast_rays``' outputs):
        ``kernels.shade_pixels`` with the scene's objects, textures and lights."""
        return kernels.shade_pixels(
            rays,
            t_hit,
            objects,
            normals,
            self.obj_R,
            self.obj_t,
            self.obj_tex,
            self.obj_tint,
            self.obj_emission,
            self.texture_stack,
            self.texel_m,
            self.light_pos,
            self.light_power,
            AMBIENT,
        )

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
            e = irradiance(points[all_idx], normals[all_idx], scene.lights)
            radiance[all_idx] = albedo * e[:, None]
    return radiance


@dataclass(frozen=True)
class RayImage:
    radiance: np.ndarray  # (H, W, 3) float32, linear
    depth_m: np.ndarray  # (H, W) float32, z in the camera frame; inf where nothing was hit
    object_index: np.ndarray  # (H, W) int32; SPHERE_OBJECT_BASE + k for wand sphere k


def camera_rays(
    camera: Camera, region: np.ndarray | None = None, *, one_thread_if_small: bool = False
) -> np.ndarray:
    """World rays (origin, direction) of ``camera``'s pixels, or of the ``region`` pixels (flat
    indices); small batches may run on the calling thread (no pool spinning under load)."""
    dirs_cam = ray_directions(camera.intrinsics).reshape(-1, 3)
    if region is not None:
        dirs_cam = np.ascontiguousarray(dirs_cam[region])
    R = camera.pose.R.astype(np.float32)
    origin = camera.pose.centre_m.astype(np.float32)
    if one_thread_if_small:
        return kernels.on_one_thread_if_small(kernels.make_rays, len(dirs_cam), dirs_cam, R, origin)
    return kernels.make_rays(dirs_cam, R, origin)


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
    rays = camera_rays(camera, region)
    t, objects, normals = scene.cast_rays(rays)
    radiance = scene.shade(rays, t, objects, normals)
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
        composite_spheres(scene.spheres, scene.lights, camera, radiance, depth, objects)
    return RayImage(radiance, depth, objects)


def render_over_background(
    moving: FrameScene,
    camera: Camera,
    background: RayImage,
    object_offset: int,
    region: np.ndarray | None = None,
) -> RayImage:
    """``camera``'s view of the static room (``background``, its cached render) with the objects
    of ``moving`` (a scene of the moving objects alone, numbered from ``object_offset``) in it.

    The same image as ``render_view`` of one scene holding both, at a fraction of the cost: only
    the ``region`` pixels (flat indices; None: all) are cast, against the small moving scene's
    own BVH rather than the whole room's, and only pixels where a moving object is nearer than
    the room are shaded. Ray-triangle hits and shading are per ray and per pixel, so each
    pixel's numbers are the ones the one-scene render computes for it (tests hold the two equal).
    """
    intr = camera.intrinsics
    H, W = intr.height_px, intr.width_px
    rays = camera_rays(camera, region, one_thread_if_small=True)
    radiance = background.radiance.reshape(-1, 3).copy()
    depth = background.depth_m.reshape(-1).copy()
    objects = background.object_index.reshape(-1).copy()
    if moving.objects:
        t, obj, normals = moving.cast_rays(rays)
        room_t = depth if region is None else depth[region]
        # strictly nearer: where a moving surface touches the room's, the room's hit stands
        near = np.flatnonzero((obj >= 0) & (t < room_t))
        pixels = near if region is None else region[near]
        radiance[pixels] = kernels.on_one_thread_if_small(
            moving.shade,
            len(near),
            np.ascontiguousarray(rays[near]),
            t[near],
            obj[near],
            np.ascontiguousarray(normals[near]),
        )
        depth[pixels] = t[near]
        objects[pixels] = obj[near] + object_offset
    image = RayImage(radiance.reshape(H, W, 3), depth.reshape(H, W), objects.reshape(H, W))
    if moving.spheres is not None:
        composite_spheres(
            moving.spheres, moving.lights, camera, image.radiance, image.depth_m, image.object_index
        )
    return image


def moving_region(camera: Camera, meshes: list, margin_px: int = 3) -> np.ndarray | None:
    """Flat indices of the pixels whose rays can meet the given meshes; None: every pixel.

    A mesh in front of the camera lies inside the box that its vertices span in normalized
    image coordinates (x/z, y/z), and a pixel's ray is a point there (``ray_directions``): the
    pixels of its projected bounding box (plus ``margin_px`` for the lens' curvature of straight
    edges) whose rays fall in that box. Where the lens folds the projection of points far
    outside the view to odd places, every pixel is tested against the box instead. A mesh that
    reaches beside or behind the camera (no such box) gets the pixels whose rays pass within its
    bounding sphere; None only when the camera is inside that sphere."""
    intr = camera.intrinsics
    H, W = intr.height_px, intr.width_px
    mask = np.zeros((H, W), bool)
    for mesh in meshes:
        v = mesh.vertices.astype(np.float64)
        if len(v) == 0:
            continue
        v_cam = v @ camera.pose.R.T + camera.pose.t_m
        z = v_cam[:, 2]
        if z.max() <= 0.0:
            continue  # wholly behind the camera: no ray (z > 0 along it) reaches it
        if z.min() < 0.05:
            if not _add_sphere_cone(mask, camera, v):
                return None
            continue
        px, _ = camera.project(v)
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - margin_px
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + margin_px
        if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
            continue
        if u0 < -W or v0 < -H or u1 > 2 * W or v1 > 2 * H:
            u0, v0, u1, v1 = 0, 0, W - 1, H - 1  # folded by the lens: test every pixel
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, W - 1), min(v1, H - 1)
        xy = v_cam[:, :2] / z[:, None]
        lo, hi = xy.min(axis=0) - RAY_BOX_MARGIN, xy.max(axis=0) + RAY_BOX_MARGIN
        rays = ray_directions(intr)[v0 : v1 + 1, u0 : u1 + 1]
        x, y = rays[..., 0], rays[..., 1]
        mask[v0 : v1 + 1, u0 : u1 + 1] |= (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])
    return np.flatnonzero(mask)


RAY_BOX_MARGIN = 5e-4  # normalized units (about half a pixel): far above float32 rounding
CONE_MARGIN_RAD = 1e-3  # about a pixel: far above float32 rounding of the cone test


def _add_sphere_cone(mask: np.ndarray, camera: Camera, vertices_m: np.ndarray) -> bool:
    """Mark in ``mask`` (H, W) every pixel whose centre ray passes within the bounding sphere of
    ``vertices_m`` (N, 3, world): a ray meets the mesh only inside that sphere, and the render
    casts one ray per pixel centre. False, marking nothing, when the camera is in the sphere."""
    lo, hi = vertices_m.min(axis=0), vertices_m.max(axis=0)
    centre = (lo + hi) / 2
    radius_m = float(np.linalg.norm(vertices_m - centre, axis=1).max()) * 1.001 + 1e-6
    c_cam = camera.pose.R @ centre + camera.pose.t_m
    dist_m = float(np.linalg.norm(c_cam))
    if dist_m <= radius_m * 1.01:
        return False
    half_angle = np.arcsin(radius_m / dist_m) + CONE_MARGIN_RAD
    dirs = ray_directions(camera.intrinsics).reshape(-1, 3)
    cos = dirs @ (c_cam / dist_m).astype(np.float32)
    cos *= _inverse_ray_lengths(camera.intrinsics)
    mask |= (cos >= np.float32(np.cos(min(half_angle, np.pi)))).reshape(mask.shape)
    return True


@functools.lru_cache(maxsize=24)
def _inverse_ray_lengths(intr: Intrinsics) -> np.ndarray:
    """(H * W,) float32: 1 / |d| of each pixel's ray direction (``ray_directions``, z = 1)."""
    d = ray_directions(intr).reshape(-1, 3).astype(np.float64)
    return (1.0 / np.sqrt(np.einsum("ij,ij->i", d, d))).astype(np.float32)
