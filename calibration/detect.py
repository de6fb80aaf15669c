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
   sphere (``calibration.sphere_geometry``, which explains the geometry): the rays of its
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
per-call overhead costs more than the arithmetic; numba kernels (``calibration.detect_kernels``)
do it in loops instead, and the candidate mask tests the spheres' colour only near pixels that
differ from the background. Each kernel keeps its slow, obvious twin (the numpy code it
replaced) here, which ``DetectorConfig(kernels="numpy")`` runs and
tests/test_calibration_detect_kernels.py checks it against; bench/bench_wand_detect.py compares
the two on simulated sessions (about 3x).

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
from typing import NamedTuple

import cv2
import numpy as np

from calibration.background import temporal_median
from calibration.detect_config import KERNELS, DetectorConfig, SphereBlob
from calibration.detect_kernels import (
    _colour_table,
    _colour_where_nb,
    _edge_points_nb,
    _ellipse_through_nb,
    _moving_nb,
    _robust_cone_nb,
)
from calibration.detect_rays import (
    _OFFSETS,
    _OUTSIDE,
    _STEP,
    _WINDOW,
    _bilinear,
    _ellipse_through,
    _outside_cone,
)
from calibration.sphere_geometry import (
    CENTRE_METHODS,
    SphereImageFit,
    _cone_residuals_px,
    _fit_cone,
    _sphere_image,
    cone_axis_from_conic,
    conic_of_sphere,
    eccentricity_bias_px,
    ellipse_centre,
    fit_conic,
    fit_sphere_cone,
    fit_sphere_outline,
    project_directions,
    rays_from_normalized,
)
from protocol.camera import Intrinsics, undistort_to_normalized

__all__ = [
    "CENTRE_METHODS",
    "KERNELS",
    "BlobCandidate",
    "DetectorConfig",
    "SphereBlob",
    "SphereDetector",
    "SphereImageFit",
    "cone_axis_from_conic",
    "conic_of_sphere",
    "eccentricity_bias_px",
    "ellipse_centre",
    "fit_conic",
    "fit_sphere_cone",
    "fit_sphere_outline",
    "project_directions",
    "rays_from_normalized",
]

log = logging.getLogger(__name__)

# ---- the detector ----------------------------------------------------------------------------


class _ConeFit(NamedTuple):
    """What ``SphereDetector._robust_fit`` keeps: the cone, its rays (N, 3), the signed
    residuals (N,) in px, and which edge points are on the outline (N,)."""

    axis: np.ndarray
    sin_alpha: float
    rays: np.ndarray
    residuals_px: np.ndarray
    keep: np.ndarray


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
        levels = np.arange(256, dtype=np.float64) / 255.0
        self._lut = (levels**self.config.gamma).astype(np.float32)
        rho = np.asarray(self.config.sphere_rgb, dtype=np.float64)[::-1]  # BGR, like the frames
        self._rho = rho / np.linalg.norm(rho)

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
        """Use a background image made elsewhere (e.g. ``calibration.background``'s median,
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
                edges, kept_fraction = _outside_cone(
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
        fit = _sphere_image(
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
        """``_candidate_mask_reference``, by numba kernels unless ``config.kernels="numpy"`` (or
        there is no background, where the colour test runs everywhere and cv2 does it faster)."""
        cfg = self.config
        if cfg.kernels == "numpy" or self._background is None:
            return self._candidate_mask_reference(image_bgr)
        small = np.ascontiguousarray(self._downsample(image_bgr))
        bg = np.ascontiguousarray(self._background)
        h, w = small.shape[:2]
        moving = _moving_nb(small.reshape(-1), bg.reshape(-1), int(cfg.background_threshold))
        near = cv2.dilate(moving.reshape(h, w), np.ones((3, 3), np.uint8))
        # the colour test only near what moved (a few % of the frame)
        colour = _colour_where_nb(
            small.reshape(-1), near.reshape(-1), _colour_table(self._hsv_bounds())
        )
        return colour.reshape(h, w)

    def _candidate_mask_reference(self, image_bgr: np.ndarray) -> np.ndarray:
        """(h, w) uint8 0/1 on the downsampled frame: the spheres' colour, and (with a
        background) near a pixel that differs from the background."""
        cfg = self.config
        small = self._downsample(image_bgr)
        mask = self._colour_mask(small)
        if self._background is not None:
            b, g, r = cv2.split(cv2.absdiff(small, self._background))
            diff = cv2.max(cv2.max(b, g), r)
            moving = cv2.threshold(diff, cfg.background_threshold, 1, cv2.THRESH_BINARY)[1]
            mask &= cv2.dilate(moving, np.ones((3, 3), np.uint8))
        return mask

    def _hsv_bounds(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        cfg = self.config
        return (cfg.hue_range[0], cfg.min_saturation, cfg.min_value), (cfg.hue_range[1], 255, 255)

    def _colour_mask(self, bgr: np.ndarray) -> np.ndarray:
        cfg = self.config
        hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
        lo = np.array([cfg.hue_range[0], cfg.min_saturation, cfg.min_value], np.uint8)
        hi = np.array([cfg.hue_range[1], 255, 255], np.uint8)
        return (cv2.inRange(hsv, lo, hi) > 0).astype(np.uint8)

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
        mask = self._colour_mask(img[y0:y1, x0:x1])
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
        """``_edge_points_reference``, by the numba kernel unless ``config.kernels="numpy"``."""
        cfg = self.config
        if cfg.kernels == "numpy":
            return self._edge_points_reference(roi, bg_roi, c, A, rays_per_px)
        roi = np.ascontiguousarray(roi)
        bg = roi if bg_roi is None else np.ascontiguousarray(bg_roi)
        return _edge_points_nb(
            roi,
            bg,
            bg_roi is not None,
            self._lut,
            self._rho,
            np.asarray(c, dtype=np.float64),
            np.asarray(A, dtype=np.float64),
            float(rays_per_px),
            int(cfg.max_rays),
            _OFFSETS,
            _STEP,
            int(cfg.clip_level),
            float(cfg.min_background_contrast),
        )

    def _edge_points_reference(
        self,
        roi: np.ndarray,
        bg_roi: np.ndarray | None,
        c: np.ndarray,
        A: np.ndarray,
        rays_per_px: float,
    ) -> tuple[np.ndarray, int]:
        """Sub-pixel edge points (ROI pixel coordinates) on rays from ``c`` across the expected
        outline ``(p - c)^T A (p - c) = 1``; and the number of rays cast."""
        cfg = self.config
        off = _OFFSETS
        evals = np.linalg.eigvalsh(A)
        r_mean = float(np.mean(1.0 / np.sqrt(np.maximum(evals, 1e-9))))
        n_rays = int(np.clip(round(rays_per_px * 2 * math.pi * r_mean), 16, cfg.max_rays))
        ang = (np.arange(n_rays) + 0.5) * (2 * math.pi / n_rays)
        dirs = np.column_stack([np.cos(ang), np.sin(ang)])
        rho = 1.0 / np.sqrt(((dirs @ A) * dirs).sum(axis=1))  # expected edge per ray
        s = np.maximum(rho[:, None] + off[None, :], 0.0)  # (R, S)
        pts = (c[None, None, :] + s[:, :, None] * dirs[:, None, :]).reshape(-1, 2)
        cover, ok, inside = self._coverage(roi, bg_roi, pts)
        # a pixel centred on a convex edge is a little less than half covered
        thr = 0.5 - 1.0 / (24.0 * max(r_mean, 1.0))
        above = cover >= thr
        cross = above[:, :-1] & ~above[:, 1:]
        dist = np.where(cross, np.abs(0.5 * (off[:-1] + off[1:]))[None, :], np.inf)
        j = np.argmin(dist, axis=1)
        rows = np.arange(n_rays)
        c0, c1 = cover[rows, j], cover[rows, j + 1]
        o_edge = off[j] + _STEP * (c0 - thr) / np.maximum(c0 - c1, 1e-9)
        ok &= np.isfinite(dist[rows, j]) & (np.abs(o_edge) <= 2.0)
        ok &= inside[:, _WINDOW].all(axis=1) & (rho + o_edge > 0.5)
        # the profile must look like an edge: the sphere just inside it
        in_sel = (off[None, :] >= o_edge[:, None] - 1.5) & (off[None, :] <= o_edge[:, None] - 1.0)
        in_cov = np.where(in_sel, cover, 0).sum(axis=1) / np.maximum(in_sel.sum(axis=1), 1)
        ok &= (in_cov >= 0.75) & (in_sel.sum(axis=1) > 0)
        edges = c[None, :] + (rho[ok] + o_edge[ok])[:, None] * dirs[ok]
        return edges, n_rays

    def _coverage(
        self, roi: np.ndarray, bg_roi: np.ndarray | None, pts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coverage (R, S) along the rays by unmixing the sphere's colour; usable rays (R,);
        samples inside the ROI (R, S)."""
        cfg = self.config
        n_off = len(_OFFSETS)
        lin = self._lut[roi]  # (h, w, 3) float32 linear BGR
        layers = [lin, (roi >= cfg.clip_level).astype(np.float32)]
        lin_bg = None
        if bg_roi is not None:
            lin_bg = self._lut[bg_roi]
            layers += [lin_bg, (bg_roi >= cfg.clip_level).astype(np.float32)]
        samples, inside_flat = _bilinear(np.concatenate(layers, axis=2), pts)
        samples = samples.reshape(-1, n_off, samples.shape[1])
        n_rays = len(samples)
        vals = samples[..., :3]
        window, outside = _WINDOW, _OUTSIDE
        # a channel saturated anywhere near the edge breaks the linear mixing: leave it out of
        # that ray (a sphere lit hard by a lamp clips its red channel first)
        clipped = samples[:, window, 3:6] > 0
        if bg_roi is not None:
            clipped |= samples[:, window, 9:12] > 0
        usable = np.logical_not(clipped.any(axis=1))  # (R, 3)
        sph = np.where(usable, self._rho[None, :], 0.0)
        sph /= np.maximum(np.linalg.norm(sph, axis=1, keepdims=True), 1e-12)
        P = usable[:, :, None] * np.eye(3)[None] - sph[:, :, None] * sph[:, None, :]
        P = P.astype(np.float32)
        # without a background model: the background colour per ray, just beyond the edge
        B = vals[:, outside].mean(axis=1)  # (R, 3)
        PB = np.matmul(P, B[:, :, None])  # (R, 3, 1); P is symmetric
        pb2 = (PB * PB).sum(axis=(1, 2))
        # (I P) . (P B) = I . (P B): one batched product per ray
        cover = 1.0 - np.matmul(vals, PB)[..., 0] / np.maximum(pb2, 1e-12)[:, None]
        ok = np.sqrt(pb2) >= cfg.min_background_contrast
        if lin_bg is not None:
            # where the frame matches the model beyond the edge, the model is what the sphere
            # hides: unmix each pixel against its own background, then interpolate coverage
            bgv = samples[..., 6:9]
            dev = np.abs(vals[:, outside] - bgv[:, outside]).max(axis=2).mean(axis=1)
            bg_ray = dev <= 0.015 + 0.08 * B.max(axis=1)
            code = usable @ np.array([1, 2, 4])
            for k in set(code[bg_ray].tolist()):
                pattern = np.array([k & 1, k & 2, k & 4], dtype=bool)
                if pattern.sum() < 2:
                    continue  # one channel cannot separate coverage from shading
                sel = bg_ray & (code == k)
                cmap = self._coverage_map(lin, lin_bg, pattern)
                ray_pts = pts.reshape(n_rays, n_off, 2)[sel].reshape(-1, 2)
                prof_k = _bilinear(cmap[..., None], ray_pts)[0].reshape(-1, n_off)
                good = np.isfinite(prof_k[:, window]).all(axis=1)
                idx = np.flatnonzero(sel)[good]
                cover[idx] = prof_k[good]
                ok[idx] = True
        ok &= usable.sum(axis=1) >= 2
        return cover, ok, inside_flat.reshape(n_rays, n_off)

    def _coverage_map(
        self, lin: np.ndarray, lin_bg: np.ndarray, channels: np.ndarray
    ) -> np.ndarray:
        """(h, w) fraction of each pixel the sphere covers, NaN where the background is too
        close to the sphere's colour (or too dark) to tell."""
        sph = np.where(channels, self._rho, 0.0)
        sph /= np.linalg.norm(sph)
        P = (np.diag(channels.astype(float)) - np.outer(sph, sph)).astype(np.float32)
        PI = lin @ P
        PB = lin_bg @ P
        pb2 = (PB * PB).sum(axis=2)
        cmap = 1.0 - (PI * PB).sum(axis=2) / np.maximum(pb2, 1e-12)
        cmap[pb2 < self.config.min_background_contrast**2] = np.nan
        return cmap

    def _robust_fit(self, edges: np.ndarray) -> _ConeFit | None:
        """``_robust_fit_reference``, by the numba kernel for ``centre_method="sphere"`` unless
        ``config.kernels="numpy"``."""
        cfg = self.config
        if cfg.kernels == "numpy" or cfg.centre_method != "sphere":
            return self._robust_fit_reference(edges)
        intr = self.intrinsics
        xy = undistort_to_normalized(edges, intr)
        try:
            ok, axis, sin_alpha, U, res, keep = _robust_cone_nb(
                np.ascontiguousarray(xy), 0.5 * (intr.fx_px + intr.fy_px)
            )
        except (ValueError, np.linalg.LinAlgError):
            return None
        return _ConeFit(axis, float(sin_alpha), U, res, keep) if ok else None

    def _robust_fit_reference(self, edges: np.ndarray) -> _ConeFit | None:
        """Fit, drop edge points far off the outline (occluders, the rod), refit."""
        intr = self.intrinsics
        f = 0.5 * (intr.fx_px + intr.fy_px)
        xy = undistort_to_normalized(edges, intr)
        U = rays_from_normalized(xy)
        keep = np.ones(len(edges), bool)
        axis, sin_alpha = np.zeros(3), float("nan")
        for _ in range(3):
            if keep.sum() < 6:
                return None
            try:
                axis, sin_alpha = _fit_cone(xy[keep], U[keep], self.config.centre_method)
            except (ValueError, np.linalg.LinAlgError):
                return None
            if not math.isfinite(sin_alpha):
                return None
            res = _cone_residuals_px(U, axis, sin_alpha, f)
            med = float(np.median(np.abs(res[keep])))
            new_keep = np.abs(res) <= max(4.0 * 1.4826 * med, 0.2)
            if (new_keep == keep).all():
                break
            keep = new_keep
        return _ConeFit(axis, sin_alpha, U, _cone_residuals_px(U, axis, sin_alpha, f), keep)

    def _ellipse_through(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``_ellipse_through``, by the numba kernel unless ``config.kernels="numpy"``."""
        if self.config.kernels == "numpy":
            return _ellipse_through(points)
        try:
            ok, centre, A = _ellipse_through_nb(np.ascontiguousarray(points, dtype=np.float64))
        except (ValueError, np.linalg.LinAlgError):
            return None
        return (centre, A) if ok else None
