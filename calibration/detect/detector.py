"""Wand-sphere detection: the sub-pixel image of each sphere's *centre* in one BGR frame.

Pipeline (about 8 ms per HD1200 frame on one core of the reference machine, detection, labelling
and the refit without the rod together; see "Speed" below):

1. Candidates on a half-size copy: pixels of the spheres' hue and saturation that also differ
   from a background model (temporal median of frames from the session: the wand moves, the room
   mostly does not), closed, outlined (``cv2.findContours``) and kept by size and shape.
2. Per candidate, at full resolution in a small window: a first outline from the moments of the
   colour mask, then rays across it, sampled bilinearly in *linear* RGB (the gamma undone). An
   edge pixel's colour is ``c * E * rho + (1 - c) * B``: its coverage ``c`` mixes the sphere's
   colour ``rho`` (matte, so its chromaticity is the same in light and in shadow, whatever the
   irradiance ``E``) with what lies behind, ``B``. Projecting out ``rho`` leaves
   ``(1 - c) * B``, so ``c`` follows without knowing the shading. ``B`` is the background model
   where the frame matches it just outside the sphere (per pixel, so a sphere in front of an edge
   in the room is unmixed correctly), else the frame 2-3 px beyond the edge on the same ray. The
   edge is where ``c`` crosses one half (less a small correction for the edge's curvature).
   Channels that clip near the edge (a sphere lit hard by a lamp turns yellow-white) are left out
   of that ray.
3. The edge points are undistorted to normalized coordinates and fitted with the image of a
   sphere (``calibration.detect.sphere_geometry``, which explains the geometry): the rays of its
   silhouette make a fixed angle with the direction of its centre, a fit of three parameters
   instead of a general conic's five, which matters for blobs of 3-5 px radius; points off the
   outline, where the rod or a hand crosses it, are dropped and the fit repeated. The cone's
   axis is the direction of the sphere's centre, *not* the centre of the ellipse (up to ~0.8 px
   apart near the edge of a wide lens at 1 m). ``centre_method="conic"`` fits a general conic
   instead and takes its cone axis; "sphere" is the default.
4. The axis goes back through the lens (distortion) to give ``centre_px``; the cone's opening
   gives the distance ``D = R / sin(alpha)``.

Adapting to a real wand: the defaults describe the simulator's matte orange spheres. Grab a few
frames of the real wand, pick pixels well inside its spheres, and build the colour model with
``DetectorConfig.from_sphere_pixels(pixels_bgr)``; set ``gamma`` to the camera's encoding
(2.2 for the ZED's default sRGB-like output). Glossy spheres break the constant-chromaticity
assumption at their highlights; use matte ones.

Speed: the per-sphere work is many operations on arrays of a few hundred values, where numpy's
per-call overhead costs more than the arithmetic; numba kernels (``calibration.detect.kernels``)
do it in loops instead, and the candidate mask tests the spheres' colour only near pixels that
differ from the background. Each kernel keeps its slow, obvious twin (the numpy code it
replaced) in ``calibration.detect._reference``, which ``DetectorConfig(kernels="numpy")`` runs
and tests/calibration/test_detect_kernels.py checks it against; bench/bench_wand_detect.py
compares the two on simulated sessions (about 3x).

JPEG: the unmixing needs each pixel's own colour. At quality 92 with 4:4:4 chroma the centres
stay within about 0.04 px (median) of the truth on the simulator; OpenCV's default 4:2:0 stores
colour per 2x2 block and the centres of 3-5 px spheres wander by about 0.3 px (median, up to
0.9 px), so wand sessions should be encoded with ``cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.detect import _reference
from calibration.detect.background import temporal_median
from calibration.detect.config import DetectorConfig, SphereBlob, colour_mask
from calibration.detect.kernels import (
    colour_table,
    colour_where_nb,
    edge_points_nb,
    ellipse_through_nb,
    moving_nb,
    robust_cone_nb,
)
from calibration.detect.rays import OFFSETS, STEP, outside_cone
from calibration.detect.sphere_geometry import ConeFit, sphere_image
from protocol.camera import Intrinsics, undistort_to_normalized

log = logging.getLogger(__name__)

# ---- the detector ----------------------------------------------------------------------------


@dataclass
class BlobCandidate:
    """A coarse blob worth refining: centre (2,) and radius in full-resolution pixels."""

    centre_px: np.ndarray
    radius_px: float


class SphereDetector:
    """Finds the wand's spheres in the frames of one sensor.

    ``intrinsics`` are that sensor's (factory) intrinsics at the capture resolution;
    ``sphere_radius_m`` is the wand's sphere radius (``WandSpec.radius_m``).
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        sphere_radius_m: float,
        config: DetectorConfig | None = None,
    ) -> None:
        if not 0.001 < sphere_radius_m < 0.5:
            raise ValueError(f"sphere_radius_m={sphere_radius_m} is not a wand sphere radius (m)")
        self.intrinsics = intrinsics
        self.sphere_radius_m = float(sphere_radius_m)
        self.config = config or DetectorConfig()
        self._background: np.ndarray | None = None  # downsampled, for the candidate mask
        self._background_full: np.ndarray | None = None  # for unmixing edge pixels
        # the unmixing's tables, made once per detector for the kernels
        self._lut = self.config.linear_levels()
        self._rho = self.config.sphere_direction_bgr()

    # ---- background ----
    @property
    def has_background(self) -> bool:
        return self._background is not None

    def fit_background(self, images_bgr: Sequence[np.ndarray]) -> None:
        """Temporal median of frames spread over the session (at least 3; 7-15 is plenty)."""
        if len(images_bgr) < 3:
            raise ValueError(f"fit_background needs at least 3 frames, got {len(images_bgr)}")
        self.set_background(temporal_median([self._check(img) for img in images_bgr]))
        log.debug("background fitted from %d frames", len(images_bgr))

    def set_background(self, background_bgr: np.ndarray) -> None:
        """Use a background image made elsewhere (e.g. ``calibration.detect.background``'s median,
        taken once for all the processes that detect in one sensor's frames)."""
        self._background_full = np.ascontiguousarray(self._check(background_bgr))
        self._background = self._downsample(self._background_full)

    def clear_background(self) -> None:
        self._background = None
        self._background_full = None

    # ---- detection ----
    def detect(self, image_bgr: np.ndarray) -> list[SphereBlob]:
        """All sphere-like blobs in the frame, best score first."""
        img = self._check(image_bgr)
        blobs = []
        for cand in self.candidates(img):
            blob = self.refine(img, cand.centre_px, cand.radius_px)
            if blob is not None:
                blobs.append(blob)
        blobs.sort(key=lambda b: -b.score)
        return blobs

    def candidates(self, image_bgr: np.ndarray) -> list[BlobCandidate]:
        """Coarse blobs of the spheres' colour that are not background, most ellipse-like first."""
        cfg = self.config
        ds = cfg.mask_downsample
        mask = cv2.morphologyEx(
            self._candidate_mask(image_bgr), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)
        )
        # contours, not connected components: the mask is sparse and this is ~30x faster
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        rmin, rmax = cfg.min_radius_px / ds, cfg.max_radius_px / ds
        out: list[tuple[float, BlobCandidate]] = []
        for cnt in contours:
            x, y, w, h = cv2.boundingRect(cnt)
            r_box = 0.5 * max(w, h)
            if not 0.5 * rmin <= r_box <= 1.3 * rmax + 1 or max(w, h) > 3 * min(w, h) + 1:
                continue
            # pixel count of the blob: the polygon through the boundary pixels' centres plus
            # the half pixel outside it all round
            area = cv2.contourArea(cnt) + 0.5 * cv2.arcLength(cnt, True) + 1.0
            if area < max(2.0, 0.5 * math.pi * rmin * rmin) or area > 1.5 * math.pi * rmax**2:
                continue
            if area < 0.45 * math.pi * r_box * r_box or area < 0.35 * w * h:
                continue
            # an upright ellipse fills pi/4 of its box; rank by how close the blob comes to that
            misfit = abs(area / (0.25 * math.pi * w * h) - 1.0)
            centre = (np.array([x + 0.5 * (w - 1), y + 0.5 * (h - 1)]) + 0.5) * ds - 0.5
            out.append((misfit, BlobCandidate(centre, max(math.sqrt(area / math.pi), r_box) * ds)))
        out.sort(key=lambda t: t[0])
        return [c for _, c in out[: cfg.max_candidates]]

    def refine(
        self,
        image_bgr: np.ndarray,
        centre_px: Sequence[float] | np.ndarray,
        radius_px: float,
        *,
        exclude_axis_px: Sequence[float] | np.ndarray | None = None,
        exclude_half_angle_deg: float = 30.0,
    ) -> SphereBlob | None:
        """Sub-pixel fit of the sphere near ``centre_px`` (coarse: within about half its radius).

        ``exclude_axis_px``: an image direction along which the outline is not used (both ways,
        within ``exclude_half_angle_deg``): the wand's rod, once the spheres are labelled. Where
        the dark rod meets a sphere the edge is mixed with the rod, not the room, and the outline
        points there lean inwards by a few hundredths of a pixel: on the last sphere, which has
        the rod on one side only, enough to shorten the wand's image by 0.02 % and grow the
        whole rig by as much (1-2 mm at 4 m).

        Returns None if no sphere-shaped outline of the spheres' colour is there.
        """
        cfg = self.config
        img = image_bgr
        H, W = img.shape[:2]
        coarse = self._coarse_ellipse(img, np.asarray(centre_px, dtype=np.float64), radius_px)
        if coarse is None:
            return None
        c, A = coarse
        cone, n_rays = None, 0
        for attempt in range(3):
            reach = 1.0 / math.sqrt(float(np.linalg.eigvalsh(A)[0])) + 5.0
            if reach > cfg.max_radius_px + 5.0:
                return None
            x0, y0 = max(int(c[0] - reach), 0), max(int(c[1] - reach), 0)
            x1, y1 = min(int(c[0] + reach) + 2, W), min(int(c[1] + reach) + 2, H)
            roi = img[y0:y1, x0:x1]
            bg = None if self._background_full is None else self._background_full[y0:y1, x0:x1]
            # the first pass only has to centre the next one: half the rays will do
            density = cfg.rays_per_px * (0.5 if attempt == 0 else 1.0)
            edges, n_rays = self._edge_points(roi, bg, c - (x0, y0), A, density)
            need = max(8.0, cfg.min_edge_fraction * n_rays)
            if len(edges) < need:
                return None
            edges += (x0, y0)
            if exclude_axis_px is not None:
                edges, kept_fraction = outside_cone(
                    edges, c, np.asarray(exclude_axis_px, dtype=np.float64), exclude_half_angle_deg
                )
                need *= kept_fraction
                n_rays = max(1, round(n_rays * kept_fraction))
                if len(edges) < need:
                    return None
            cone = self._robust_fit(edges)
            if cone is None or cone.keep.sum() < need:
                return None
            if np.sqrt(np.mean(cone.residuals_px[cone.keep] ** 2)) > 3 * cfg.max_fit_rms_px:
                return None  # not a sphere's outline: no point in another pass
            outline = self._ellipse_through(edges[cone.keep])
            if outline is None:
                return None
            moved = float(np.linalg.norm(outline[0] - c))
            c, A = outline
            if moved < 0.1:
                break
        assert cone is not None
        keep = cone.keep
        fit = sphere_image(
            cone.axis, cone.sin_alpha, cone.rays, self.intrinsics, self.sphere_radius_m
        )
        rms = float(np.sqrt(np.mean(fit.residuals_px[keep] ** 2)))
        radius = float(np.linalg.norm(edges[keep] - fit.ellipse_centre_px, axis=1).mean())
        if rms > cfg.max_fit_rms_px or not cfg.min_radius_px <= radius <= cfg.max_radius_px:
            return None
        if not math.isfinite(fit.distance_m):
            return None
        frac = min(float(keep.sum()) / n_rays, 1.0)
        f = 0.5 * (self.intrinsics.fx_px + self.intrinsics.fy_px)
        return SphereBlob(
            centre_px=(float(fit.centre_px[0]), float(fit.centre_px[1])),
            ellipse_centre_px=(float(fit.ellipse_centre_px[0]), float(fit.ellipse_centre_px[1])),
            radius_px=radius,
            score=frac / (1.0 + (rms / 0.15) ** 2),
            distance_m=float(fit.distance_m),
            centre_normalized=(float(fit.centre_normalized[0]), float(fit.centre_normalized[1])),
            focal_px=f,
            edge_rms_px=rms,
            n_edge_points=int(keep.sum()),
        )

    # ---- internals ----
    def _check(self, img: np.ndarray) -> np.ndarray:
        intr = self.intrinsics
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"expected an (H, W, 3) uint8 BGR image, got {img.shape} {img.dtype}")
        if img.shape[:2] != (intr.height_px, intr.width_px):
            raise ValueError(
                f"image is {img.shape[1]}x{img.shape[0]} but the intrinsics are for "
                f"{intr.width_px}x{intr.height_px}"
            )
        return img

    def _downsample(self, img: np.ndarray) -> np.ndarray:
        ds = self.config.mask_downsample
        if ds == 1:
            return img
        return cv2.resize(
            img, (img.shape[1] // ds, img.shape[0] // ds), interpolation=cv2.INTER_AREA
        )

    def _candidate_mask(self, image_bgr: np.ndarray) -> np.ndarray:
        """(h, w) uint8 0/1 on the downsampled frame: the spheres' colour, and (with a
        background) near a pixel that differs from the background. By numba kernels unless
        ``config.kernels="numpy"`` (or there is no background, where the colour test runs
        everywhere and cv2 does it faster): then ``_reference.candidate_mask``."""
        cfg = self.config
        if cfg.kernels == "numpy" or self._background is None:
            return _reference.candidate_mask(self._downsample(image_bgr), self._background, cfg)
        small = np.ascontiguousarray(self._downsample(image_bgr))
        bg = np.ascontiguousarray(self._background)
        h, w = small.shape[:2]
        moving = moving_nb(small.reshape(-1), bg.reshape(-1), int(cfg.background_threshold))
        near = cv2.dilate(moving.reshape(h, w), np.ones((3, 3), np.uint8))
        # the colour test only near what moved (a few % of the frame)
        colour = colour_where_nb(
            small.reshape(-1), near.reshape(-1), colour_table(cfg.hsv_bounds())
        )
        return colour.reshape(h, w)

    def _coarse_ellipse(
        self, img: np.ndarray, c: np.ndarray, r: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Centre and shape ``A`` (edge at ``d^T A d = 1``) from the full-resolution colour mask
        around a candidate: a uniform ellipse's second moments are a quarter of its axes squared.
        """
        H, W = img.shape[:2]
        half = math.ceil(1.5 * r + 4)
        x0, y0 = max(int(c[0]) - half, 0), max(int(c[1]) - half, 0)
        x1, y1 = min(int(c[0]) + half + 1, W), min(int(c[1]) + half + 1, H)
        mask = colour_mask(img[y0:y1, x0:x1], self.config)
        n, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if n < 2:
            return None
        d = np.linalg.norm(cents[1:] + np.array([x0, y0]) - c, axis=1)
        areas = stats[1:, cv2.CC_STAT_AREA].astype(float)
        i = int(np.argmax(areas / (1.0 + d / max(r, 1.0)))) + 1
        m = cv2.moments((labels == i).astype(np.uint8), binaryImage=True)
        if m["m00"] < math.pi * (0.7 * self.config.min_radius_px) ** 2:
            return None
        centre = np.array([m["m10"] / m["m00"] + x0, m["m01"] / m["m00"] + y0])
        cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
        cov += np.eye(2) / 12.0  # the pixels' own extent
        try:
            A = np.linalg.inv(4.0 * cov)
        except np.linalg.LinAlgError:
            return None
        return centre, A

    def _edge_points(
        self,
        roi: np.ndarray,
        bg_roi: np.ndarray | None,
        c: np.ndarray,
        A: np.ndarray,
        rays_per_px: float,
    ) -> tuple[np.ndarray, int]:
        """Sub-pixel edge points (ROI pixel coordinates) on rays from ``c`` across the expected
        outline ``(p - c)^T A (p - c) = 1``, and the number of rays cast: by the numba kernel
        unless ``config.kernels="numpy"`` (then ``_reference.edge_points``)."""
        cfg = self.config
        if cfg.kernels == "numpy":
            return _reference.edge_points(roi, bg_roi, c, A, rays_per_px, cfg)
        roi = np.ascontiguousarray(roi)
        bg = roi if bg_roi is None else np.ascontiguousarray(bg_roi)
        return edge_points_nb(
            roi,
            bg,
            bg_roi is not None,
            self._lut,
            self._rho,
            np.asarray(c, dtype=np.float64),
            np.asarray(A, dtype=np.float64),
            float(rays_per_px),
            int(cfg.max_rays),
            OFFSETS,
            STEP,
            int(cfg.clip_level),
            float(cfg.min_background_contrast),
        )

    def _robust_fit(self, edges: np.ndarray) -> ConeFit | None:
        """Fit, drop edge points far off the outline (occluders, the rod), refit: by the numba
        kernel for ``centre_method="sphere"`` unless ``config.kernels="numpy"`` (then
        ``_reference.robust_fit``)."""
        cfg = self.config
        if cfg.kernels == "numpy" or cfg.centre_method != "sphere":
            return _reference.robust_fit(edges, self.intrinsics, cfg)
        intr = self.intrinsics
        xy = undistort_to_normalized(edges, intr)
        try:
            ok, axis, sin_alpha, U, res, keep = robust_cone_nb(
                np.ascontiguousarray(xy), 0.5 * (intr.fx_px + intr.fy_px)
            )
        except (ValueError, np.linalg.LinAlgError):
            return None
        return ConeFit(axis, float(sin_alpha), U, res, keep) if ok else None

    def _ellipse_through(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Centre and shape ``A`` of the ellipse through (N, 2) px: by the numba kernel unless
        ``config.kernels="numpy"`` (then ``_reference.ellipse_through``)."""
        if self.config.kernels == "numpy":
            return _reference.ellipse_through(points)
        try:
            ok, centre, A = ellipse_through_nb(np.ascontiguousarray(points, dtype=np.float64))
        except (ValueError, np.linalg.LinAlgError):
            return None
        return (centre, A) if ok else None
