"""Camera rays through real lens models: each pixel's ray comes from inverting the sensor's
OpenCV distortion, so distorted sensor images and undistorted virtual pinholes come out of the
same code."""

from __future__ import annotations

import functools

import numpy as np

from protocol.camera import Intrinsics, undistort_to_normalized


@functools.lru_cache(maxsize=24)
def ray_directions(intr: Intrinsics) -> np.ndarray:
    """(H, W, 3) float32 camera-frame ray directions with z = 1, one per pixel centre.

    For a distorted sensor these come from inverting the distortion iteratively, so projecting a
    ray back through ``cv2.projectPoints`` lands on its pixel to far below 0.01 px.
    """
    u, v = np.meshgrid(
        np.arange(intr.width_px, dtype=np.float64), np.arange(intr.height_px, dtype=np.float64)
    )
    return directions_for_pixels(intr, np.stack([u, v], axis=-1))


def directions_for_pixels(intr: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """(..., 2) pixel coordinates -> (..., 3) float32 camera-frame directions with z = 1.

    Each point is undistorted on its own, so a pixel's direction does not depend on which other
    pixels are in the batch (the sphere compositor relies on it)."""
    shape = pixels.shape[:-1]
    xy = undistort_to_normalized(pixels.reshape(-1, 2), intr)
    d = np.ones((len(xy), 3), np.float32)
    d[:, :2] = xy
    return d.reshape(*shape, 3)
