"""The geometry of a sphere's image: its centre's direction and distance from its outline.

The rays ``u`` of a sphere's silhouette make a fixed angle ``alpha`` with the direction ``a`` of
its centre, ``a . u = cos(alpha)``, which is linear in ``w = a / cos(alpha)``
(``fit_sphere_cone``: three parameters instead of a general conic's five, which matters for blobs
of 3-5 px radius). This is the tangent cone ``x^T C x = 0`` with
``C = a a^T - cos^2(alpha) I`` (``conic_of_sphere``); its axis ``a`` is the eigenvector of
``C``'s eigenvalue of distinct sign and is the direction of the sphere's centre, *not* the centre
of the ellipse (``ellipse_centre``), which lies further from the principal point by
``f tan(theta) sin^2(alpha) / (cos^2(theta) - sin^2(alpha))`` (``eccentricity_bias_px``: up to
~0.8 px near the edge of a wide lens at 1 m). ``method="conic"`` (the detector's
``centre_method``) fits a general conic instead (``fit_conic``) and takes its cone axis
(``cone_axis_from_conic``); on the simulator's 3-5 px spheres it is as good in the median but
its worst cases are several times worse, so "sphere" is the default. The axis goes back through
the lens (distortion, ``project_directions``) to give the centre's pixel; the cone's opening
gives the distance ``D = R / sin(alpha)``. ``fit_sphere_outline`` does it all for one outline;
``calibration.detect.detector`` uses the pieces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from protocol.camera import Intrinsics, undistort_to_normalized

CENTRE_METHODS = ("sphere", "conic")


def rays_from_normalized(xy: np.ndarray) -> np.ndarray:
    """(N, 2) normalized coordinates -> (N, 3) unit rays."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    u = np.column_stack([xy, np.ones(len(xy))])
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def fit_sphere_cone(rays: np.ndarray) -> tuple[np.ndarray, float]:
    """Silhouette rays (N, 3) of a sphere -> (unit centre direction (3,), sin(alpha)).

    Solves ``w . u_i = 1`` in least squares, ``w = a / cos(alpha)``: a circle on the unit
    sphere. Its residual ``1 - w . u`` is the angular error times ``tan(alpha)``, the same all
    round the outline, so the fit is effectively geometric.
    """
    U = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    if len(U) < 3:
        raise ValueError(f"need at least 3 silhouette rays, got {len(U)}")
    w, *_ = np.linalg.lstsq(U, np.ones(len(U)), rcond=None)
    n = float(np.linalg.norm(w))
    a = w / n
    if a[2] < 0:
        a = -a
    sin_alpha = math.sqrt(max(1.0 - 1.0 / (n * n), 0.0)) if n > 1.0 else float("nan")
    return a, sin_alpha


def conic_of_sphere(axis: np.ndarray, sin_alpha: float) -> np.ndarray:
    """The 3x3 conic (normalized homogeneous coordinates) of a sphere seen along ``axis``."""
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    a = a / np.linalg.norm(a)
    return np.outer(a, a) - (1.0 - sin_alpha**2) * np.eye(3)


def fit_conic(xy: np.ndarray) -> np.ndarray:
    """General conic through (N >= 5, 2) normalized points: 3x3 symmetric C, x^T C x = 0.

    Direct algebraic fit, with the points centred and scaled to unit spread first (Hartley) so
    the SVD is well conditioned.
    """
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(p) < 5:
        raise ValueError(f"a conic needs at least 5 points, got {len(p)}")
    m = p.mean(axis=0)
    s = math.sqrt(2.0) / max(float(np.sqrt(((p - m) ** 2).sum(axis=1)).mean()), 1e-12)
    q = (p - m) * s
    x, y = q[:, 0], q[:, 1]
    A = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    a, b, c, d, e, f = vt[-1]
    Cs = np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])
    T = np.array([[s, 0.0, -s * m[0]], [0.0, s, -s * m[1]], [0.0, 0.0, 1.0]])
    C = T.T @ Cs @ T
    return C / np.linalg.norm(C)


def cone_axis_from_conic(C: np.ndarray) -> tuple[np.ndarray, float]:
    """Axis (unit, z > 0) and sin(alpha) of the circular cone ``x^T C x = 0``.

    For ``C = a a^T - cos^2(alpha) I`` the eigenvalues are ``sin^2(alpha)`` (eigenvector ``a``)
    and ``-cos^2(alpha)`` twice: the axis is the eigenvector of the eigenvalue of distinct sign,
    and ``sin^2(alpha) = l1 / (l1 - l2)`` with ``l2`` the mean of the other two. A fitted conic's
    pair is not exactly equal; their mean is used.
    """
    Cm = np.asarray(C, dtype=np.float64).reshape(3, 3)
    Cm = 0.5 * (Cm + Cm.T)
    vals, vecs = np.linalg.eigh(Cm)
    if (vals > 0).sum() == 2:  # make the distinct eigenvalue the positive one
        vals, vecs = -vals[::-1], vecs[:, ::-1]
    if (vals > 0).sum() != 1:
        raise ValueError(f"conic eigenvalues {vals} do not describe a real cone")
    i = int(np.argmax(vals))
    l1 = float(vals[i])
    l2 = float(np.delete(vals, i).mean())
    a = vecs[:, i]
    if a[2] < 0:
        a = -a
    return a, math.sqrt(l1 / (l1 - l2))


def ellipse_centre(C: np.ndarray) -> np.ndarray:
    """Centre (2,) of the ellipse ``x^T C x = 0`` (normalized coordinates)."""
    Cm = np.asarray(C, dtype=np.float64)
    return np.linalg.solve(Cm[:2, :2], -Cm[:2, 2])


def eccentricity_bias_px(focal_px: float, theta_rad: float, sin_alpha: float) -> float:
    """Distance from the projected sphere centre to the imaged ellipse's centre (pinhole), px."""
    s2 = sin_alpha**2
    return focal_px * math.tan(theta_rad) * s2 / (math.cos(theta_rad) ** 2 - s2)


def project_directions(directions: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 3) camera-frame directions (z > 0) -> (N, 2) distorted pixels."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    zero = np.zeros(3)
    px, _ = cv2.projectPoints(d, zero, zero, intr.K, intr.dist_array)
    return px.reshape(-1, 2)


@dataclass(frozen=True)
class SphereImageFit:
    """What ``fit_sphere_outline`` recovers from one sphere's outline."""

    centre_px: np.ndarray  # (2,)
    ellipse_centre_px: np.ndarray  # (2,)
    centre_normalized: np.ndarray  # (2,)
    axis: np.ndarray  # (3,) unit direction of the centre
    sin_alpha: float
    distance_m: float
    residuals_px: np.ndarray  # (N,) signed, per edge point (positive: outside the fitted outline)


class ConeFit(NamedTuple):
    """A sphere's cone fitted robustly to its edge points: the centre's direction ``axis`` (3,),
    ``sin_alpha``, the edge points' rays (N, 3), their signed residuals (N,) in px, and which
    edge points are on the outline (N,)."""

    axis: np.ndarray
    sin_alpha: float
    rays: np.ndarray
    residuals_px: np.ndarray
    keep: np.ndarray


def fit_sphere_outline(
    edge_px: np.ndarray, intr: Intrinsics, sphere_radius_m: float, method: str = "sphere"
) -> SphereImageFit:
    """(N, 2) distorted edge pixels of one sphere -> its centre's image and its distance."""
    xy = undistort_to_normalized(np.asarray(edge_px, dtype=np.float64).reshape(-1, 2), intr)
    U = rays_from_normalized(xy)
    axis, sin_alpha = fit_cone(xy, U, method)
    return sphere_image(axis, sin_alpha, U, intr, sphere_radius_m)


def fit_cone(xy: np.ndarray, U: np.ndarray, method: str) -> tuple[np.ndarray, float]:
    if method == "sphere":
        return fit_sphere_cone(U)
    if method == "conic":
        return cone_axis_from_conic(fit_conic(xy))
    raise ValueError(f"unknown centre method {method!r}; use one of {CENTRE_METHODS}")


def cone_residuals_px(
    U: np.ndarray, axis: np.ndarray, sin_alpha: float, focal_px: float
) -> np.ndarray:
    """Angle of each ray outside the cone, in px (f per radian: close enough for residuals)."""
    ang = np.arccos(np.clip(U @ axis, -1.0, 1.0)) - math.asin(min(max(sin_alpha, 0.0), 1.0))
    return ang * focal_px


def sphere_image(
    axis: np.ndarray, sin_alpha: float, U: np.ndarray, intr: Intrinsics, sphere_radius_m: float
) -> SphereImageFit:
    e_norm = ellipse_centre(conic_of_sphere(axis, sin_alpha))
    pts = project_directions(np.array([axis, [e_norm[0], e_norm[1], 1.0]]), intr)
    f = 0.5 * (intr.fx_px + intr.fy_px)
    return SphereImageFit(
        centre_px=pts[0],
        ellipse_centre_px=pts[1],
        centre_normalized=axis[:2] / axis[2],
        axis=axis,
        sin_alpha=sin_alpha,
        distance_m=sphere_radius_m / sin_alpha if sin_alpha > 0 else float("nan"),
        residuals_px=cone_residuals_px(U, axis, sin_alpha, f),
    )
