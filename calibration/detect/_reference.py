"""The wand detector's slow, obvious twins: the numpy and OpenCV code the numba kernels
(``calibration.detect.kernels``) replaced, kept apart from the fast paths in
``calibration.detect.detector``. ``DetectorConfig(kernels="numpy")`` runs them instead of the
kernels; tests/calibration/test_detect_kernels.py feeds each pair the same inputs and checks they
agree (the same edge points to 1e-4 px, the same masks bit for bit).

  bilinear, edge_points  <-> kernels._bilinear_nb, kernels.edge_points_nb (with _coverage and
                             _coverage_map: rays, bilinear samples, unmixing, edge crossing)
  robust_fit             <-> kernels.robust_cone_nb ("sphere" centre method)
  ellipse_through        <-> kernels.ellipse_through_nb
  candidate_mask         <-> kernels.moving_nb, kernels.colour_where_nb

The maths is the detector's (``calibration.detect.detector``'s docstring explains the unmixing
and the fit); these functions favour being read over being fast.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from calibration.detect.config import DetectorConfig, colour_mask
from calibration.detect.rays import OFFSETS, OUTSIDE, STEP, WINDOW
from calibration.detect.sphere_geometry import (
    ConeFit,
    cone_residuals_px,
    ellipse_centre,
    fit_cone,
    fit_conic,
    rays_from_normalized,
)
from protocol.camera import Intrinsics, undistort_to_normalized


def candidate_mask(
    small_bgr: np.ndarray, background_small: np.ndarray | None, config: DetectorConfig
) -> np.ndarray:
    """(h, w) uint8 0/1 on the downsampled frame: the spheres' colour, and (with a
    background) near a pixel that differs from the background."""
    mask = colour_mask(small_bgr, config)
    if background_small is not None:
        b, g, r = cv2.split(cv2.absdiff(small_bgr, background_small))
        diff = cv2.max(cv2.max(b, g), r)
        moving = cv2.threshold(diff, config.background_threshold, 1, cv2.THRESH_BINARY)[1]
        mask &= cv2.dilate(moving, np.ones((3, 3), np.uint8))
    return mask


def ellipse_through(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre and shape ``A`` (``(p - c)^T A (p - c) = 1``) of the ellipse through (N, 2) px."""
    try:
        C = fit_conic(points)
        centre = ellipse_centre(C)
    except (ValueError, np.linalg.LinAlgError):
        return None
    k = float(centre @ C[:2, :2] @ centre - C[2, 2])
    A = C[:2, :2] / k
    if not np.isfinite(A).all() or np.linalg.eigvalsh(A)[0] <= 0:
        return None
    return centre, A


def bilinear(img: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples (N, C) of an (h, w, C) image at (N, 2) (x, y); and which were inside."""
    h, w, nc = img.shape
    x, y = pts[:, 0], pts[:, 1]
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xc = np.clip(x, 0, w - 1.001)
    yc = np.clip(y, 0, h - 1.001)
    x0 = xc.astype(np.intp)
    y0 = yc.astype(np.intp)
    fx = (xc - x0)[:, None].astype(np.float32)
    fy = (yc - y0)[:, None].astype(np.float32)
    flat = img.reshape(-1, nc)
    i00 = y0 * w + x0
    v00, v01 = flat[i00], flat[i00 + 1]
    v10, v11 = flat[i00 + w], flat[i00 + w + 1]
    top = v00 + (v01 - v00) * fx
    bot = v10 + (v11 - v10) * fx
    return top + (bot - top) * fy, inside


def robust_fit(edges: np.ndarray, intrinsics: Intrinsics, config: DetectorConfig) -> ConeFit | None:
    """Fit, drop edge points far off the outline (occluders, the rod), refit."""
    f = 0.5 * (intrinsics.fx_px + intrinsics.fy_px)
    xy = undistort_to_normalized(edges, intrinsics)
    U = rays_from_normalized(xy)
    keep = np.ones(len(edges), bool)
    axis, sin_alpha = np.zeros(3), float("nan")
    for _ in range(3):
        if keep.sum() < 6:
            return None
        try:
            axis, sin_alpha = fit_cone(xy[keep], U[keep], config.centre_method)
        except (ValueError, np.linalg.LinAlgError):
            return None
        if not math.isfinite(sin_alpha):
            return None
        res = cone_residuals_px(U, axis, sin_alpha, f)
        med = float(np.median(np.abs(res[keep])))
        new_keep = np.abs(res) <= max(4.0 * 1.4826 * med, 0.2)
        if (new_keep == keep).all():
            break
        keep = new_keep
    return ConeFit(axis, sin_alpha, U, cone_residuals_px(U, axis, sin_alpha, f), keep)


def edge_points(
    roi: np.ndarray,
    bg_roi: np.ndarray | None,
    c: np.ndarray,
    A: np.ndarray,
    rays_per_px: float,
    config: DetectorConfig,
) -> tuple[np.ndarray, int]:
    """Sub-pixel edge points (ROI pixel coordinates) on rays from ``c`` across the expected
    outline ``(p - c)^T A (p - c) = 1``; and the number of rays cast."""
    off = OFFSETS
    evals = np.linalg.eigvalsh(A)
    r_mean = float(np.mean(1.0 / np.sqrt(np.maximum(evals, 1e-9))))
    n_rays = int(np.clip(round(rays_per_px * 2 * math.pi * r_mean), 16, config.max_rays))
    ang = (np.arange(n_rays) + 0.5) * (2 * math.pi / n_rays)
    dirs = np.column_stack([np.cos(ang), np.sin(ang)])
    rho = 1.0 / np.sqrt(((dirs @ A) * dirs).sum(axis=1))  # expected edge per ray
    s = np.maximum(rho[:, None] + off[None, :], 0.0)  # (R, S)
    pts = (c[None, None, :] + s[:, :, None] * dirs[:, None, :]).reshape(-1, 2)
    cover, ok, inside = _coverage(roi, bg_roi, pts, config)
    # a pixel centred on a convex edge is a little less than half covered
    thr = 0.5 - 1.0 / (24.0 * max(r_mean, 1.0))
    above = cover >= thr
    cross = above[:, :-1] & ~above[:, 1:]
    dist = np.where(cross, np.abs(0.5 * (off[:-1] + off[1:]))[None, :], np.inf)
    j = np.argmin(dist, axis=1)
    rows = np.arange(n_rays)
    c0, c1 = cover[rows, j], cover[rows, j + 1]
    o_edge = off[j] + STEP * (c0 - thr) / np.maximum(c0 - c1, 1e-9)
    ok &= np.isfinite(dist[rows, j]) & (np.abs(o_edge) <= 2.0)
    ok &= inside[:, WINDOW].all(axis=1) & (rho + o_edge > 0.5)
    # the profile must look like an edge: the sphere just inside it
    in_sel = (off[None, :] >= o_edge[:, None] - 1.5) & (off[None, :] <= o_edge[:, None] - 1.0)
    in_cov = np.where(in_sel, cover, 0).sum(axis=1) / np.maximum(in_sel.sum(axis=1), 1)
    ok &= (in_cov >= 0.75) & (in_sel.sum(axis=1) > 0)
    edges = c[None, :] + (rho[ok] + o_edge[ok])[:, None] * dirs[ok]
    return edges, n_rays


def _coverage(
    roi: np.ndarray, bg_roi: np.ndarray | None, pts: np.ndarray, config: DetectorConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coverage (R, S) along the rays by unmixing the sphere's colour; usable rays (R,);
    samples inside the ROI (R, S)."""
    lut, rho = config.linear_levels(), config.sphere_direction_bgr()
    n_off = len(OFFSETS)
    lin = lut[roi]  # (h, w, 3) float32 linear BGR
    layers = [lin, (roi >= config.clip_level).astype(np.float32)]
    lin_bg = None
    if bg_roi is not None:
        lin_bg = lut[bg_roi]
        layers += [lin_bg, (bg_roi >= config.clip_level).astype(np.float32)]
    samples, inside_flat = bilinear(np.concatenate(layers, axis=2), pts)
    samples = samples.reshape(-1, n_off, samples.shape[1])
    n_rays = len(samples)
    vals = samples[..., :3]
    # a channel saturated anywhere near the edge breaks the linear mixing: leave it out of
    # that ray (a sphere lit hard by a lamp clips its red channel first)
    clipped = samples[:, WINDOW, 3:6] > 0
    if bg_roi is not None:
        clipped |= samples[:, WINDOW, 9:12] > 0
    usable = np.logical_not(clipped.any(axis=1))  # (R, 3)
    sph = np.where(usable, rho[None, :], 0.0)
    sph /= np.maximum(np.linalg.norm(sph, axis=1, keepdims=True), 1e-12)
    P = usable[:, :, None] * np.eye(3)[None] - sph[:, :, None] * sph[:, None, :]
    P = P.astype(np.float32)
    # without a background model: the background colour per ray, just beyond the edge
    B = vals[:, OUTSIDE].mean(axis=1)  # (R, 3)
    PB = np.matmul(P, B[:, :, None])  # (R, 3, 1); P is symmetric
    pb2 = (PB * PB).sum(axis=(1, 2))
    # (I P) . (P B) = I . (P B): one batched product per ray
    cover = 1.0 - np.matmul(vals, PB)[..., 0] / np.maximum(pb2, 1e-12)[:, None]
    ok = np.sqrt(pb2) >= config.min_background_contrast
    if lin_bg is not None:
        # where the frame matches the model beyond the edge, the model is what the sphere
        # hides: unmix each pixel against its own background, then interpolate coverage
        bgv = samples[..., 6:9]
        dev = np.abs(vals[:, OUTSIDE] - bgv[:, OUTSIDE]).max(axis=2).mean(axis=1)
        bg_ray = dev <= 0.015 + 0.08 * B.max(axis=1)
        code = usable @ np.array([1, 2, 4])
        for k in set(code[bg_ray].tolist()):
            pattern = np.array([k & 1, k & 2, k & 4], dtype=bool)
            if pattern.sum() < 2:
                continue  # one channel cannot separate coverage from shading
            sel = bg_ray & (code == k)
            cmap = _coverage_map(lin, lin_bg, pattern, rho, config.min_background_contrast)
            ray_pts = pts.reshape(n_rays, n_off, 2)[sel].reshape(-1, 2)
            prof_k = bilinear(cmap[..., None], ray_pts)[0].reshape(-1, n_off)
            good = np.isfinite(prof_k[:, WINDOW]).all(axis=1)
            idx = np.flatnonzero(sel)[good]
            cover[idx] = prof_k[good]
            ok[idx] = True
    ok &= usable.sum(axis=1) >= 2
    return cover, ok, inside_flat.reshape(n_rays, n_off)


def _coverage_map(
    lin: np.ndarray,
    lin_bg: np.ndarray,
    channels: np.ndarray,
    rho: np.ndarray,
    min_background_contrast: float,
) -> np.ndarray:
    """(h, w) fraction of each pixel the sphere covers, NaN where the background is too
    close to the sphere's colour (or too dark) to tell."""
    sph = np.where(channels, rho, 0.0)
    sph /= np.linalg.norm(sph)
    P = (np.diag(channels.astype(float)) - np.outer(sph, sph)).astype(np.float32)
    PI = lin @ P
    PB = lin_bg @ P
    pb2 = (PB * PB).sum(axis=2)
    cmap = 1.0 - (PI * PB).sum(axis=2) / np.maximum(pb2, 1e-12)
    cmap[pb2 < min_background_contrast**2] = np.nan
    return cmap
