"""Compiled per-pixel kernels for the renderer and the sensor (Numba, parallel over pixels).

Each has a slow, obvious twin in numpy (``sim.render.shade_reference``, ``sim.sensor.expose``)
that the tests compare it with; these exist only because the numpy versions spend most of their
time allocating temporaries (about 4x slower at HD1200, see BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from protocol.numba_threads import use_openmp_threads

use_openmp_threads()

import numba  # noqa: E402
from numba import njit, prange  # noqa: E402

SMALL_N = 200_000  # below this many rays or pixels a kernel runs on the calling thread


def on_one_thread_if_small(kernel: Callable[..., np.ndarray], n: int, *args: object) -> np.ndarray:
    """``kernel(*args)``, on the calling thread alone when ``n`` is small.

    Waking the thread pool costs more than a few ten thousand pixels of work, and on a busy
    machine (two sim agents on two cores) the pool's idle workers spin on the cores the other
    process needs. The compiled loop is the same either way, so is every pixel's value."""
    if n >= SMALL_N:
        return kernel(*args)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        return kernel(*args)
    finally:
        numba.set_num_threads(threads)


@njit(parallel=True, cache=True, fastmath=True)
def make_rays(dirs_cam: np.ndarray, R: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame directions -> (N, 6) world rays (origin, R^T d) for open3d."""
    n = dirs_cam.shape[0]
    rays = np.empty((n, 6), np.float32)
    for i in prange(n):
        x, y, z = dirs_cam[i, 0], dirs_cam[i, 1], dirs_cam[i, 2]
        rays[i, 0] = origin[0]
        rays[i, 1] = origin[1]
        rays[i, 2] = origin[2]
        for k in range(3):
            rays[i, 3 + k] = R[0, k] * x + R[1, k] * y + R[2, k] * z
    return rays


@njit(parallel=True, cache=True, fastmath=True)
def shade_pixels(
    rays: np.ndarray,  # (N, 6) float32
    t_hit: np.ndarray,  # (N,) float32
    obj: np.ndarray,  # (N,) int32, -1 for nothing
    normals: np.ndarray,  # (N, 3) float32
    obj_R: np.ndarray,  # (K, 3, 3) float32 local-from-world rotation
    obj_t: np.ndarray,  # (K, 3) float32
    obj_tex: np.ndarray,  # (K,) int32
    obj_tint: np.ndarray,  # (K, 3) float32
    obj_emission: np.ndarray,  # (K,) float32, > 0 for emissive
    textures: np.ndarray,  # (T, S, S, 3) float32
    texel_m: np.ndarray,  # (T,) float32
    light_pos: np.ndarray,  # (L, 3) float32
    light_power: np.ndarray,  # (L,) float32
    ambient: float,
) -> np.ndarray:
    n = rays.shape[0]
    out = np.zeros((n, 3), np.float32)
    for i in prange(n):
        k = obj[i]
        if k < 0:
            continue
        t = t_hit[i]
        px = rays[i, 0] + t * rays[i, 3]
        py = rays[i, 1] + t * rays[i, 4]
        pz = rays[i, 2] + t * rays[i, 5]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        if nx * rays[i, 3] + ny * rays[i, 4] + nz * rays[i, 5] > 0:
            nx, ny, nz = -nx, -ny, -nz
        # object-local point and normal, for triplanar texture coordinates
        lx = obj_R[k, 0, 0] * px + obj_R[k, 0, 1] * py + obj_R[k, 0, 2] * pz + obj_t[k, 0]
        ly = obj_R[k, 1, 0] * px + obj_R[k, 1, 1] * py + obj_R[k, 1, 2] * pz + obj_t[k, 1]
        lz = obj_R[k, 2, 0] * px + obj_R[k, 2, 1] * py + obj_R[k, 2, 2] * pz + obj_t[k, 2]
        anx = abs(obj_R[k, 0, 0] * nx + obj_R[k, 0, 1] * ny + obj_R[k, 0, 2] * nz)
        any_ = abs(obj_R[k, 1, 0] * nx + obj_R[k, 1, 1] * ny + obj_R[k, 1, 2] * nz)
        anz = abs(obj_R[k, 2, 0] * nx + obj_R[k, 2, 1] * ny + obj_R[k, 2, 2] * nz)
        if anx >= any_ and anx >= anz:
            u, v = ly, lz
        elif any_ >= anz:
            u, v = lx, lz
        else:
            u, v = lx, ly
        tid = obj_tex[k]
        inv = 1.0 / texel_m[tid]
        # bilinear, wrapping texture lookup
        size = textures.shape[1]
        fu = u * inv
        fv = v * inv
        bu = np.floor(fu)
        bv = np.floor(fv)
        au = fu - bu
        av = fv - bv
        iu0 = int(bu) % size
        iv0 = int(bv) % size
        iu1 = (iu0 + 1) % size
        iv1 = (iv0 + 1) % size
        w00 = (1 - au) * (1 - av)
        w01 = au * (1 - av)
        w10 = (1 - au) * av
        w11 = au * av
        if obj_emission[k] > 0:
            scale = obj_emission[k]
        else:
            e = ambient
            for j in range(light_pos.shape[0]):
                dx = light_pos[j, 0] - px
                dy = light_pos[j, 1] - py
                dz = light_pos[j, 2] - pz
                d2 = dx * dx + dy * dy + dz * dz
                cos = (dx * nx + dy * ny + dz * nz) / np.sqrt(d2)
                if cos > 0:
                    e += light_power[j] * cos / max(d2, 0.25)
            scale = e
        for c in range(3):
            alb = (
                textures[tid, iv0, iu0, c] * w00
                + textures[tid, iv0, iu1, c] * w01
                + textures[tid, iv1, iu0, c] * w10
                + textures[tid, iv1, iu1, c] * w11
            )
            out[i, c] = alb * obj_tint[k, c] * scale
    return out


@njit(inline="always")
def _hash_normal(key: np.uint64, index: np.uint64) -> float:
    """A unit-variance, zero-mean draw that depends only on (key, index).

    splitmix64 gives 64 random bits; the sum of their four 16-bit quarters (Irwin-Hall, n = 4) is
    close to Gaussian (tails cut at 3.5 sigma), which is all sensor noise needs, at a fraction of
    Box-Muller's cost.
    """
    z = key + index * np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    m = np.uint64(0xFFFF)
    total = (z & m) + ((z >> np.uint64(16)) & m) + ((z >> np.uint64(32)) & m) + (z >> np.uint64(48))
    # each quarter is uniform on [0, 65535]: mean 32767.5, variance (65536^2 - 1) / 12
    return (float(total) - 131070.0) * (1.0 / 37837.23)


GAMMA_LUT_SIZE = 4096


@njit(parallel=True, cache=True, fastmath=True)
def expose_pixels(
    radiance: np.ndarray,  # (H, W, 3) float32
    vignette: np.ndarray,  # (H, W) float32
    noise_key: np.uint64,
    gain_e: float,  # electrons per unit radiance
    read_noise_e: float,
    full_well_e: float,
    gamma_lut: np.ndarray,  # (GAMMA_LUT_SIZE + 1,) uint8: linear [0, 1] -> 8-bit
) -> np.ndarray:
    H, W = vignette.shape
    out = np.empty((H, W, 3), np.uint8)
    rn2 = read_noise_e * read_noise_e
    scale = GAMMA_LUT_SIZE / full_well_e
    for y in prange(H):
        for x in range(W):
            g = gain_e * vignette[y, x]
            for c in range(3):
                s = max(radiance[y, x, c] * g, 0.0)
                idx = np.uint64((y * W + x) * 3 + c)
                s += _hash_normal(noise_key, idx) * np.sqrt(s + rn2)
                q = int(s * scale + 0.5)
                q = min(max(q, 0), GAMMA_LUT_SIZE)
                out[y, x, c] = gamma_lut[q]
    return out


def noise_normals(noise_key: int, shape: tuple[int, ...]) -> np.ndarray:
    """The same normal draws ``expose_pixels`` uses, as an array (for the reference twin)."""
    return _noise_array(np.uint64(noise_key), int(np.prod(shape))).reshape(shape)


@njit(parallel=True, cache=True)
def _noise_array(key: np.uint64, n: int) -> np.ndarray:
    out = np.empty(n, np.float32)
    for i in prange(n):
        out[i] = _hash_normal(key, np.uint64(i))
    return out
