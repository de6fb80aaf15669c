"""What the wand detector is told and what it returns: ``DetectorConfig`` (how the wand's
spheres look, learned from a few pixels with ``from_sphere_pixels``) and ``SphereBlob`` (one
detected sphere). The detector itself is ``calibration.detect.detector``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.detect.sphere_geometry import CENTRE_METHODS

KERNELS = ("numba", "numpy")


@dataclass(frozen=True, kw_only=True)
class DetectorConfig:
    """How the wand's spheres look. Colours are for BGR uint8 frames (OpenCV convention).

    ``hue_range`` (OpenCV hue, 0-180), ``min_saturation`` and ``min_value`` (0-255) pick candidate
    pixels; ``sphere_rgb`` is the spheres' colour in *linear* RGB (only its direction matters),
    used to measure how much of each edge pixel the sphere covers.
    """

    hue_range: tuple[int, int] = (4, 30)
    min_saturation: int = 100
    min_value: int = 30
    sphere_rgb: tuple[float, float, float] = (0.95, 0.42, 0.08)
    gamma: float = 2.2
    min_radius_px: float = 2.0
    max_radius_px: float = 80.0
    background_threshold: int = 18  # max-channel |frame - background| in 8-bit levels
    mask_downsample: int = 2
    max_candidates: int = 40
    max_fit_rms_px: float = 0.35
    min_edge_fraction: float = 0.5
    clip_level: int = 250  # 8-bit value at which a channel is treated as saturated
    min_background_contrast: float = 0.02  # linear; edge rays against a sphere-coloured or
    # black background carry no coverage information and are dropped
    centre_method: str = "sphere"
    rays_per_px: float = 2.0  # edge rays per pixel of circumference
    max_rays: int = 128
    kernels: str = "numba"  # "numpy": the per-sphere work in the slow, obvious numpy twins of
    # the numba kernels (same results to ~1e-6 px; for tests and benchmarks)

    def __post_init__(self) -> None:
        h0, h1 = self.hue_range
        if not 0 <= h0 < h1 <= 180:
            raise ValueError(
                f"DetectorConfig.hue_range={self.hue_range} must satisfy 0<=lo<hi<=180"
            )
        for name in ("min_saturation", "min_value", "background_threshold", "clip_level"):
            v = getattr(self, name)
            if not 0 <= v <= 255:
                raise ValueError(f"DetectorConfig.{name}={v} must be an 8-bit level (0-255)")
        rgb = np.asarray(self.sphere_rgb, dtype=float)
        if rgb.shape != (3,) or (rgb < 0).any() or rgb.sum() <= 0:
            raise ValueError(f"DetectorConfig.sphere_rgb={self.sphere_rgb} must be 3 values >= 0")
        if not 1.0 <= self.gamma <= 3.0:
            raise ValueError(f"DetectorConfig.gamma={self.gamma} must be between 1 and 3")
        if not 1.0 <= self.min_radius_px < self.max_radius_px:
            raise ValueError(
                f"DetectorConfig radii {self.min_radius_px}..{self.max_radius_px} px must satisfy "
                "1 <= min < max"
            )
        if self.mask_downsample not in (1, 2, 4):
            raise ValueError(f"DetectorConfig.mask_downsample={self.mask_downsample} not in 1,2,4")
        if self.centre_method not in CENTRE_METHODS:
            raise ValueError(
                f"DetectorConfig.centre_method={self.centre_method!r} not in {CENTRE_METHODS}"
            )
        if self.kernels not in KERNELS:
            raise ValueError(f"DetectorConfig.kernels={self.kernels!r} not in {KERNELS}")
        if not 0.0 < self.min_edge_fraction <= 1.0:
            raise ValueError(
                f"DetectorConfig.min_edge_fraction={self.min_edge_fraction} not in (0,1]"
            )

    @classmethod
    def from_sphere_pixels(cls, pixels_bgr: np.ndarray, **overrides: object) -> DetectorConfig:
        """A config whose colour model is learned from pixels well inside a real wand's spheres.

        ``pixels_bgr``: (N, 3) uint8 (or an image crop). The hue window is the central 98% of the
        pixels' hues widened by 4; the saturation floor is 60% of their 5th percentile.
        """
        px = np.asarray(pixels_bgr, dtype=np.uint8).reshape(-1, 1, 3)
        if len(px) < 10:
            raise ValueError(f"need at least 10 sphere pixels to learn a colour, got {len(px)}")
        hsv = cv2.cvtColor(px, cv2.COLOR_BGR2HSV).reshape(-1, 3).astype(float)
        h_lo, h_hi = np.percentile(hsv[:, 0], [1, 99])
        gamma = float(overrides.get("gamma", cls.gamma))  # type: ignore[arg-type]
        lin = (px.reshape(-1, 3)[:, ::-1].astype(float) / 255.0) ** gamma
        rgb = np.median(lin, axis=0)
        learned: dict[str, object] = {
            "hue_range": (max(0, int(h_lo) - 4), min(180, math.ceil(h_hi) + 4)),
            "min_saturation": int(0.6 * np.percentile(hsv[:, 1], 5)),
            "sphere_rgb": tuple(float(v) for v in rgb / rgb.max()),
        }
        learned.update(overrides)
        return cls(**learned)  # type: ignore[arg-type]

    def hsv_bounds(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """The spheres' colour window in OpenCV HSV: (low, high), each (hue, saturation, value)."""
        return (self.hue_range[0], self.min_saturation, self.min_value), (
            self.hue_range[1],
            255,
            255,
        )

    def linear_levels(self) -> np.ndarray:
        """(256,) float32: each 8-bit level with the camera's ``gamma`` undone (linear light)."""
        levels = np.arange(256, dtype=np.float64) / 255.0
        return (levels**self.gamma).astype(np.float32)

    def sphere_direction_bgr(self) -> np.ndarray:
        """(3,) the spheres' linear colour as a unit vector in B, G, R order, like the frames."""
        rho = np.asarray(self.sphere_rgb, dtype=np.float64)[::-1]
        return rho / np.linalg.norm(rho)


def colour_mask(bgr: np.ndarray, config: DetectorConfig) -> np.ndarray:
    """(h, w) uint8 0/1: the pixels of an (h, w, 3) BGR image inside the config's HSV window."""
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    lo = np.array([config.hue_range[0], config.min_saturation, config.min_value], np.uint8)
    hi = np.array([config.hue_range[1], 255, 255], np.uint8)
    return (cv2.inRange(hsv, lo, hi) > 0).astype(np.uint8)


@dataclass(frozen=True, kw_only=True)
class SphereBlob:
    """One detected sphere.

    ``centre_px``: distorted pixel of the projection of the sphere's centre (bias-corrected);
    ``ellipse_centre_px``: the centre of its imaged outline (what a plain ellipse fit reports);
    ``centre_normalized``: the undistorted normalized coordinates (x/z, y/z) of ``centre_px``;
    ``radius_px``: mean radius of the outline; ``distance_m``: camera centre to sphere centre
    from the cone's opening; ``focal_px``: pixels per unit of normalized coordinates, to turn
    tolerances in px into normalized units; ``score`` in (0, 1], higher is better.
    """

    centre_px: tuple[float, float]
    ellipse_centre_px: tuple[float, float]
    radius_px: float
    score: float
    distance_m: float = float("nan")
    centre_normalized: tuple[float, float] = (float("nan"), float("nan"))
    focal_px: float = float("nan")
    edge_rms_px: float = float("nan")
    n_edge_points: int = 0
