"""Sampling across a sphere's outline for the wand detector (``calibration.detect``): where the
samples of a ray lie (``_OFFSETS`` around the expected edge, ``_STEP`` px apart), bilinear
sampling with an inside flag, the ellipse through five edge points, and the edge points that
leave along the wand's rod. Their numba twins are in ``detect_kernels.py``.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.sphere_geometry import ellipse_centre, fit_conic

_STEP = 0.25  # px between samples along a ray


_OFFSETS = np.arange(-3.0, 3.0 + 1e-9, _STEP)  # samples relative to the expected edge
_WINDOW = (_OFFSETS >= -2.0) & (_OFFSETS <= 3.0)  # where clipping or leaving the ROI matters
_OUTSIDE = _OFFSETS >= 2.0  # where the background is read


def _outside_cone(
    edges: np.ndarray, centre: np.ndarray, axis: np.ndarray, half_angle_deg: float
) -> tuple[np.ndarray, float]:
    """Edge points not within ``half_angle_deg`` of ``±axis`` seen from ``centre``, and the
    fraction of the outline that leaves."""
    a = axis / max(float(np.linalg.norm(axis)), 1e-12)
    v = edges - centre
    cos = np.abs(v @ a) / np.maximum(np.linalg.norm(v, axis=1), 1e-12)
    keep = cos < math.cos(math.radians(half_angle_deg))
    return edges[keep], 1.0 - 2.0 * half_angle_deg / 180.0


def _ellipse_through(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
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


def _bilinear(img: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
