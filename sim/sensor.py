"""The image sensor: exposure, vignetting, photon and read noise, gamma and 8-bit quantisation.

A global-shutter AR0234 behind a wide lens, in numbers that give images like a ZED X's indoors:
about 1% noise in mid-grey, stronger in the dark, a mild fall-off to the corners. The noise is
drawn from a generator the caller keys per frame, so the same frame always gets the same noise.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from protocol.camera import Intrinsics


@dataclass(frozen=True, kw_only=True)
class SensorSpec:
    exposure_gain: float = 1.0
    full_well_e: float = 9000.0  # electrons at white
    read_noise_e: float = 6.0
    vignetting: float = 0.25  # relative loss at the image corner
    gamma: float = 2.2

    def __post_init__(self) -> None:
        if self.exposure_gain <= 0:
            raise ValueError(f"SensorSpec.exposure_gain={self.exposure_gain} must be positive")
        if not 0 <= self.vignetting < 1:
            raise ValueError(f"SensorSpec.vignetting={self.vignetting} must be in [0, 1)")


def encode_ideal(radiance: np.ndarray) -> np.ndarray:
    """Linear radiance -> 8-bit with gamma and nothing else (virtual cameras, ground truth)."""
    return to_uint8(radiance, 2.2)


def to_uint8(linear: np.ndarray, gamma: float) -> np.ndarray:
    v = np.clip(linear, 0.0, 1.0, dtype=np.float32)
    np.power(v, np.float32(1.0 / gamma), out=v)
    v *= 255.0
    v += 0.5
    return v.astype(np.uint8)


def vignette(intr: Intrinsics, strength: float) -> np.ndarray:
    """(H, W) float32 gain, 1 at the principal point and 1 - strength at the farthest corner."""
    u = (np.arange(intr.width_px, dtype=np.float32) - intr.cx_px) / intr.fx_px
    v = (np.arange(intr.height_px, dtype=np.float32) - intr.cy_px) / intr.fy_px
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    falloff = 1.0 / (1.0 + r2) ** 2  # cos^4 law
    corner = falloff.min()
    return (1.0 - strength * (1.0 - falloff) / max(1.0 - corner, 1e-6)).astype(np.float32)


def gamma_lut(gamma: float, size: int) -> np.ndarray:
    """(size + 1,) uint8: linear value i/size -> gamma-encoded 8-bit."""
    return to_uint8(np.linspace(0.0, 1.0, size + 1, dtype=np.float32), gamma)


def expose(radiance: np.ndarray, intr: Intrinsics, spec: SensorSpec, noise_key: int) -> np.ndarray:
    """Linear radiance (H, W, 3) -> the 8-bit RGB image the sensor delivers.

    ``noise_key`` (a 64-bit integer) fixes the noise, so a frame always gets the same noise. This
    is the compiled path; ``expose_reference`` is its slow numpy twin and draws the same noise.
    """
    from sim.kernels import GAMMA_LUT_SIZE, expose_pixels

    return expose_pixels(
        np.ascontiguousarray(radiance, np.float32),
        _vignette_cached(intr, spec.vignetting),
        np.uint64(noise_key),
        spec.exposure_gain * spec.full_well_e,
        spec.read_noise_e,
        spec.full_well_e,
        gamma_lut(spec.gamma, GAMMA_LUT_SIZE),
    )


@functools.lru_cache(maxsize=16)
def _vignette_cached(intr: Intrinsics, strength: float) -> np.ndarray:
    return vignette(intr, strength)


def expose_reference(
    radiance: np.ndarray, intr: Intrinsics, spec: SensorSpec, noise_key: int
) -> np.ndarray:
    """Slow numpy twin of ``expose`` (exact gamma instead of the lookup table)."""
    from sim.kernels import noise_normals

    signal = radiance * (spec.exposure_gain * spec.full_well_e)
    signal *= vignette(intr, spec.vignetting)[..., None]
    np.maximum(signal, 0.0, out=signal)
    noise = noise_normals(noise_key, signal.shape)
    noise *= np.sqrt(signal + spec.read_noise_e**2)
    signal += noise
    signal *= 1.0 / spec.full_well_e
    return to_uint8(signal, spec.gamma)
