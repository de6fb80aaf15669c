"""Projection of 3D Gaussians to screen-space ellipses, and its hand-written backward (numba).

Forward, per Gaussian i (float64 inside, float32 out; see ``reconstructor.raster`` for the
conventions):

    q̂ = q / |q|,  R_q = rotation(q̂),  S = diag(exp(log_scales)),  Σ3D = R_q S Sᵀ R_qᵀ
    t = W x + t_w                         (viewmat = [[W, t_w], [0, 1]])
    culled if t_z < near_m or t_z > far_m
    u_t = clamp(t_x / t_z, -lim_x-, lim_x+)  with
        lim_x+ = (width - 0.5 - cx) / fx + 0.3 · width / (2 fx)
        lim_x- = (cx + 0.5) / fx + 0.3 · width / (2 fx)
    (likewise v_t with fy, cy, height; for a centred principal point this is 3DGS's 1.3 × the
    frustum tangent; the image edges lie at -0.5 and width - 0.5 with pixel centres at integers)
    J = [[fx / t_z, 0, -fx u_t / t_z], [0, fy / t_z, -fy v_t / t_z]]
    Σ2D = J W Σ3D Wᵀ Jᵀ + eps2d · I,  conic = Σ2D⁻¹  (culled if det Σ2D <= 0)
    radius = ceil(sigma_extent · sqrt(λ_max(Σ2D)))   (culled if 0)
    mean2d = (fx t_x / t_z + cx, fy t_y / t_z + cy)
    the Gaussian covers the tiles holding a pixel centre inside the square mean2d ± radius
    (culled if that square holds no pixel centre of the image) and inside the box where its
    alpha can reach alpha_min (HX, HY below; no tile if opacity < alpha_min)
    opacity = sigmoid(logit)

The backward applies the chain rule through the same steps: conic → Σ2D (−C G C) → J and
W Σ3D Wᵀ → Σ3D → (R_q, S) → (q̂, log_scales) → q; mean2d and J → t → x. The clamp of u_t, v_t
passes no gradient to t_x, t_y where it is active (as autograd's clamp).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

# Columns of the per-Gaussian array the projection hands to the raster kernels: mean2d, conic
# (a, b, c) of [[a, b], [b, c]], opacity, camera depth, colour, and HX, HY: the half-width and
# half-height in pixels of the region where alpha can reach alpha_min,
# dᵀ conic d <= 2 ln(opacity / alpha_min) (widened by SPAN_SLACK; HY < 0 if the opacity is
# below alpha_min), and LOG2O = log2(opacity) (only where HY >= 0).
MX, MY, CA, CB, CC, OPA, DEPTH, CR, CG, CB_, HX, HY, LOG2O = range(13)
PROJ_COLS = 16  # one 64-byte cache line
SPAN_SLACK = 1e-3  # relative widening: the exact per-pixel test decides inside the region


@njit(cache=True, fastmath=True)
def _quat_rot(w, x, y, z):
    """Row-major 3x3 rotation of a unit quaternion (w, x, y, z)."""
    return (
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )


@njit(cache=True, fastmath=True)
def _mm(a, b):
    """A B for row-major 3x3 tuples."""
    return (
        a[0] * b[0] + a[1] * b[3] + a[2] * b[6],
        a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
        a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
        a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
        a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
        a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[3] + a[8] * b[6],
        a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
        a[6] * b[2] + a[7] * b[5] + a[8] * b[8],
    )


@njit(cache=True, fastmath=True)
def _tr(a):
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


@njit(cache=True, fastmath=True)
def _camera_point(i, means, viewmat):
    """Camera-frame position (t_x, t_y, t_z) of Gaussian i."""
    x0 = np.float64(means[i, 0])
    x1 = np.float64(means[i, 1])
    x2 = np.float64(means[i, 2])
    tx = viewmat[0, 0] * x0 + viewmat[0, 1] * x1 + viewmat[0, 2] * x2 + viewmat[0, 3]
    ty = viewmat[1, 0] * x0 + viewmat[1, 1] * x1 + viewmat[1, 2] * x2 + viewmat[1, 3]
    tz = viewmat[2, 0] * x0 + viewmat[2, 1] * x1 + viewmat[2, 2] * x2 + viewmat[2, 3]
    return tx, ty, tz


@njit(cache=True, fastmath=True)
def _gaussian_frame(i, means, quats, scales, viewmat):
    """Rotation, scales, camera point and camera-space covariance of Gaussian i."""
    qw = np.float64(quats[i, 0])
    qx = np.float64(quats[i, 1])
    qy = np.float64(quats[i, 2])
    qz = np.float64(quats[i, 3])
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    rq = _quat_rot(qw / qn, qx / qn, qy / qn, qz / qn)
    sx = np.float64(scales[i, 0])
    sy = np.float64(scales[i, 1])
    sz = np.float64(scales[i, 2])
    m = (
        rq[0] * sx, rq[1] * sy, rq[2] * sz,
        rq[3] * sx, rq[4] * sy, rq[5] * sz,
        rq[6] * sx, rq[7] * sy, rq[8] * sz,
    )  # fmt: skip
    w = (
        viewmat[0, 0], viewmat[0, 1], viewmat[0, 2],
        viewmat[1, 0], viewmat[1, 1], viewmat[1, 2],
        viewmat[2, 0], viewmat[2, 1], viewmat[2, 2],
    )  # fmt: skip
    tx, ty, tz = _camera_point(i, means, viewmat)
    wm = _mm(w, m)
    cov_cam = _mm(wm, _tr(wm))  # W M Mᵀ Wᵀ
    return rq, (sx, sy, sz), m, w, tx, ty, tz, cov_cam


@njit(cache=True, fastmath=True)
def _jacobian(tx, ty, tz, intr, lims):
    """EWA Jacobian entries (j00, j02, j11, j12) and the clamped tangents (u_t, v_t)."""
    fx, fy = intr[0], intr[1]
    u_t = min(max(tx / tz, -lims[0]), lims[1])
    v_t = min(max(ty / tz, -lims[2]), lims[3])
    return fx / tz, -fx * u_t / tz, fy / tz, -fy * v_t / tz, u_t, v_t


@njit(cache=True, fastmath=True)
def _cov2d(j00, j02, j11, j12, c):
    """J C Jᵀ for J = [[j00, 0, j02], [0, j11, j12]] and symmetric row-major C."""
    a0 = j00 * c[0] + j02 * c[6]
    a1 = j00 * c[1] + j02 * c[7]
    a2 = j00 * c[2] + j02 * c[8]
    b1 = j11 * c[4] + j12 * c[7]
    b2 = j11 * c[5] + j12 * c[8]
    return a0 * j00 + a2 * j02, a1 * j11 + a2 * j12, b1 * j11 + b2 * j12


@njit(parallel=True, cache=True, fastmath=True)
def project_forward(  # noqa: PLR0915
    means, quats, scales, opacity, log_ratio, colors, viewmat, intr, lims, width, height, tile,
    near, far, eps2d, sigma_extent,
):  # fmt: skip
    """Project N Gaussians.

    Args: means (N, 3), quats (N, 4), scales (N, 3) = exp(log_scales), opacity (N,),
    log_ratio (N,) = ln(opacity / alpha_min), colors (N, 3) float32 (the exponentials come
    from numpy, whose vectorised exp is 10x faster than a scalar call per element);
    viewmat (4, 4), intr (fx, fy, cx, cy), lims (lim_x-, lim_x+, lim_y-, lim_y+) float64.

    Returns: proj (N, PROJ_COLS) float32 (see the column constants), radii (N,) int32
    (0 = culled), rect (N, 4) int32 inclusive tile rectangle (x0, x1, y0, y1).
    """
    n = means.shape[0]
    # np.empty and explicit zeros: in a parallel function numba compiles every np.zeros into
    # a parallel loop of its own, which costs seconds of compile time each.
    proj = np.empty((n, PROJ_COLS), np.float32)
    radii = np.empty(n, np.int32)
    rect = np.empty((n, 4), np.int32)
    for i in prange(n):
        for c in range(PROJ_COLS):
            proj[i, c] = 0.0
        radii[i] = 0
        for c in range(4):
            rect[i, c] = 0
        tx, ty, tz = _camera_point(i, means, viewmat)
        if tz < near or tz > far:
            continue
        j00, j02, j11, j12, _, _ = _jacobian(tx, ty, tz, intr, lims)
        mx = intr[0] * tx / tz + intr[2]
        my = intr[1] * ty / tz + intr[3]
        # cheap early cull of Gaussians far outside the image (a third of a fused cloud is):
        # λ_max(J Σ Jᵀ) <= |J|_F² max(scales)², so this radius bounds the true one
        s_max = max(scales[i, 0], scales[i, 1], scales[i, 2])
        r_bound = (
            sigma_extent
            * math.sqrt((j00 * j00 + j02 * j02 + j11 * j11 + j12 * j12) * s_max * s_max + eps2d)
            + 1.0
        )
        if mx + r_bound < 0.0 or my + r_bound < 0.0 or mx - r_bound > width - 1:
            continue
        if my - r_bound > height - 1:
            continue
        _, _, _, _, _, _, _, cov = _gaussian_frame(i, means, quats, scales, viewmat)
        s00, s01, s11 = _cov2d(j00, j02, j11, j12, cov)
        s00 += eps2d
        s11 += eps2d
        det = s00 * s11 - s01 * s01
        if det <= 0.0:
            continue
        mid = 0.5 * (s00 + s11)
        lam = mid + math.sqrt(max(mid * mid - det, 0.0))
        r = math.ceil(sigma_extent * math.sqrt(lam))
        if r <= 0 or mx + r < 0.0 or my + r < 0.0 or mx - r > width - 1 or my - r > height - 1:
            continue
        u0 = max(math.ceil(mx - r), 0)
        u1 = min(math.floor(mx + r), width - 1)
        v0 = max(math.ceil(my - r), 0)
        v1 = min(math.floor(my + r), height - 1)
        if u0 > u1 or v0 > v1:
            continue
        radii[i] = r
        proj[i, MX] = mx
        proj[i, MY] = my
        proj[i, CA] = s11 / det
        proj[i, CB] = -s01 / det
        proj[i, CC] = s00 / det
        proj[i, OPA] = opacity[i]
        proj[i, DEPTH] = tz
        proj[i, CR] = colors[i, 0]
        proj[i, CG] = colors[i, 1]
        proj[i, CB_] = colors[i, 2]
        if log_ratio[i] > 0:
            # max |dx| over dᵀ Σ⁻¹ d <= span is sqrt(span Σ_xx), likewise for dy
            span = 2.0 * np.float64(log_ratio[i]) * (1.0 + SPAN_SLACK) + SPAN_SLACK
            proj[i, HX] = math.sqrt(span * s00)
            proj[i, HY] = math.sqrt(span * s11)
            proj[i, LOG2O] = math.log2(opacity[i])
            # Tiles: only those the alpha_min region can reach (a trained model's faint
            # Gaussians reach a small part of their 3-sigma square, many reach nothing). One
            # pixel wider than the region as stored in float32, which is what the raster
            # kernels test each tile against: the lists lose only entries that draw nothing.
            hx, hy = proj[i, HX], proj[i, HY]
            u0 = max(u0, math.ceil(proj[i, MX] - hx) - 1)
            u1 = min(u1, math.floor(proj[i, MX] + hx) + 1)
            v0 = max(v0, math.ceil(proj[i, MY] - hy) - 1)
            v1 = min(v1, math.floor(proj[i, MY] + hy) + 1)
        else:
            proj[i, HY] = -1.0
            u1 = v1 = -1  # draws nowhere: in no tile's list
        if u0 <= u1 and v0 <= v1:
            rect[i, 0] = u0 // tile
            rect[i, 1] = u1 // tile
            rect[i, 2] = v0 // tile
            rect[i, 3] = v1 // tile
        else:  # an empty rectangle (x1 < x0, y1 < y0): binned nowhere
            rect[i, 0], rect[i, 1], rect[i, 2], rect[i, 3] = 0, -1, 0, -1
    return proj, radii, rect


@njit(parallel=True, cache=True, fastmath=True)
def project_backward(  # noqa: PLR0915
    means, quats, scales, opacity, viewmat, intr, lims, eps2d, records, goffsets,
):  # fmt: skip
    """Sum each Gaussian's per-pair records, then chain them back to its parameters.

    Args: the forward's inputs; records (M, 9) float32 from ``kernels.raster_backward`` =
    dL/d(mean2d x, y, conic a, b, c, opacity, r, g, b) per (tile, Gaussian) pair, grouped by
    Gaussian; goffsets (N + 1,) from ``kernels.bin_gaussians``: Gaussian i's records are rows
    goffsets[i]..goffsets[i + 1] - 1 (none if culled).

    Returns: dL/d means (N, 3), quats (N, 4), log_scales (N, 3), logits (N,), colors (N, 3),
    float32; zero for culled Gaussians.
    """
    n = means.shape[0]
    g_means = np.empty((n, 3), np.float32)  # np.empty: see project_forward
    g_quats = np.empty((n, 4), np.float32)
    g_scales = np.empty((n, 3), np.float32)
    g_logits = np.empty(n, np.float32)
    g_colors = np.empty((n, 3), np.float32)
    fx, fy = intr[0], intr[1]
    for i in prange(n):
        for c in range(3):
            g_means[i, c] = g_scales[i, c] = g_colors[i, c] = 0.0
        for c in range(4):
            g_quats[i, c] = 0.0
        g_logits[i] = 0.0
        if goffsets[i] == goffsets[i + 1]:
            continue
        # summed in pair order, so the result does not depend on the thread schedule
        gmx = gmy = ga = gb = gc = go = 0.0
        for k in range(goffsets[i], goffsets[i + 1]):
            rec = records[k]
            gmx += rec[0]
            gmy += rec[1]
            ga += rec[2]
            gb += rec[3]
            gc += rec[4]
            go += rec[5]
            for c in range(3):
                g_colors[i, c] += rec[6 + c]
        rq, s, m, w, tx, ty, tz, cov = _gaussian_frame(i, means, quats, scales, viewmat)
        j00, j02, j11, j12, u_t, v_t = _jacobian(tx, ty, tz, intr, lims)
        s00, s01, s11 = _cov2d(j00, j02, j11, j12, cov)
        s00 += eps2d
        s11 += eps2d
        det = s00 * s11 - s01 * s01
        ca, cb, cc = s11 / det, -s01 / det, s00 / det
        # conic -> Σ2D: dL/dΣ = -C G C with G the full-matrix gradient (off-diagonals halved)
        gb *= 0.5
        p00, p01 = ga * ca + gb * cb, ga * cb + gb * cc
        p10, p11 = gb * ca + gc * cb, gb * cb + gc * cc
        g00 = -(ca * p00 + cb * p10)
        g01 = -(ca * p01 + cb * p11)
        g11 = -(cb * p01 + cc * p11)
        # Σ2D = J C Jᵀ: dL/dC = Jᵀ G J, dL/dJ = 2 G J C
        jm = (j00, 0.0, j02, 0.0, j11, j12)
        gj = (
            g00 * j00,
            g00 * 0.0 + g01 * j11,
            g00 * j02 + g01 * j12,
            g01 * j00,
            g11 * j11,
            g01 * j02 + g11 * j12,
        )  # fmt: skip  (G J, 2x3)
        g_cov = (
            jm[0] * gj[0] + jm[3] * gj[3], jm[0] * gj[1] + jm[3] * gj[4],
            jm[0] * gj[2] + jm[3] * gj[5],
            jm[1] * gj[0] + jm[4] * gj[3], jm[1] * gj[1] + jm[4] * gj[4],
            jm[1] * gj[2] + jm[4] * gj[5],
            jm[2] * gj[0] + jm[5] * gj[3], jm[2] * gj[1] + jm[5] * gj[4],
            jm[2] * gj[2] + jm[5] * gj[5],
        )  # fmt: skip
        d_j00 = 2.0 * (gj[0] * cov[0] + gj[1] * cov[3] + gj[2] * cov[6])
        d_j02 = 2.0 * (gj[0] * cov[2] + gj[1] * cov[5] + gj[2] * cov[8])
        d_j11 = 2.0 * (gj[3] * cov[1] + gj[4] * cov[4] + gj[5] * cov[7])
        d_j12 = 2.0 * (gj[3] * cov[2] + gj[4] * cov[5] + gj[5] * cov[8])
        # J -> t (u_t = t_x / t_z unless clamped; then it is a constant)
        tz2 = tz * tz
        gtx = 0.0
        gty = 0.0
        gtz = -d_j00 * fx / tz2 - d_j11 * fy / tz2 + d_j02 * fx * u_t / tz2 + d_j12 * fy * v_t / tz2
        if -lims[0] <= tx / tz <= lims[1]:
            gtx += -d_j02 * fx / tz2
            gtz += d_j02 * fx * tx / (tz2 * tz)
        if -lims[2] <= ty / tz <= lims[3]:
            gty += -d_j12 * fy / tz2
            gtz += d_j12 * fy * ty / (tz2 * tz)
        # mean2d -> t
        gtx += gmx * fx / tz
        gty += gmy * fy / tz
        gtz -= (gmx * fx * tx + gmy * fy * ty) / tz2
        for k in range(3):
            g_means[i, k] = w[k] * gtx + w[3 + k] * gty + w[6 + k] * gtz
        # C = W Σ3D Wᵀ -> Σ3D = M Mᵀ -> M = R_q S
        g_sig = _mm(_mm(_tr(w), g_cov), w)
        g_m = _mm(g_sig, m)  # half of dL/dM
        g_r = (
            2.0 * g_m[0] * s[0], 2.0 * g_m[1] * s[1], 2.0 * g_m[2] * s[2],
            2.0 * g_m[3] * s[0], 2.0 * g_m[4] * s[1], 2.0 * g_m[5] * s[2],
            2.0 * g_m[6] * s[0], 2.0 * g_m[7] * s[1], 2.0 * g_m[8] * s[2],
        )  # fmt: skip
        for k in range(3):
            gs = 2.0 * (g_m[k] * rq[k] + g_m[3 + k] * rq[3 + k] + g_m[6 + k] * rq[6 + k])
            g_scales[i, k] = gs * s[k]
        # R_q(q̂) -> q̂ -> q
        qw, qx = np.float64(quats[i, 0]), np.float64(quats[i, 1])
        qy, qz = np.float64(quats[i, 2]), np.float64(quats[i, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        w_, x_, y_, z_ = qw / qn, qx / qn, qy / qn, qz / qn
        gw = 2.0 * (-z_ * g_r[1] + y_ * g_r[2] + z_ * g_r[3] - x_ * g_r[5] - y_ * g_r[6]
                    + x_ * g_r[7])  # fmt: skip
        gx = 2.0 * (y_ * g_r[1] + z_ * g_r[2] + y_ * g_r[3] - 2.0 * x_ * g_r[4] - w_ * g_r[5]
                    + z_ * g_r[6] + w_ * g_r[7] - 2.0 * x_ * g_r[8])  # fmt: skip
        gy = 2.0 * (-2.0 * y_ * g_r[0] + x_ * g_r[1] + w_ * g_r[2] + x_ * g_r[3] + z_ * g_r[5]
                    - w_ * g_r[6] + z_ * g_r[7] - 2.0 * y_ * g_r[8])  # fmt: skip
        gz = 2.0 * (-2.0 * z_ * g_r[0] - w_ * g_r[1] + x_ * g_r[2] + w_ * g_r[3]
                    - 2.0 * z_ * g_r[4] + y_ * g_r[5] + x_ * g_r[6] + y_ * g_r[7])  # fmt: skip
        dot = w_ * gw + x_ * gx + y_ * gy + z_ * gz
        g_quats[i, 0] = (gw - w_ * dot) / qn
        g_quats[i, 1] = (gx - x_ * dot) / qn
        g_quats[i, 2] = (gy - y_ * dot) / qn
        g_quats[i, 3] = (gz - z_ * dot) / qn
        o = np.float64(opacity[i])
        g_logits[i] = go * o * (1.0 - o)
    return g_means, g_quats, g_scales, g_logits, g_colors


class Projected(NamedTuple):
    """What the raster kernels need from the projection (numpy, float32 unless noted)."""

    proj: np.ndarray  # (N, PROJ_COLS), see the column constants
    radii: np.ndarray  # (N,) int32, 0 = culled
    rect: np.ndarray  # (N, 4) int32 inclusive tile rectangle (x0, x1, y0, y1)
    scales: np.ndarray  # (N, 3) exp(log_scales)
    opacity: np.ndarray  # (N,) sigmoid(logits)
    intr: np.ndarray  # (4,) float64 fx, fy, cx, cy
    lims: np.ndarray  # (4,) float64 frustum tangent limits


def project(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    logits: np.ndarray,
    colors: np.ndarray,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    tile: int,
    near: float,
    far: float,
    eps2d: float,
    sigma_extent: float,
    alpha_min: float,
) -> Projected:
    """Project N Gaussians: float32 (N, ...) arrays as ``rasterize`` takes them, viewmat (4, 4)
    and K (3, 3) float64."""
    intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64)
    lims = frustum_limits(intr, width, height)
    scales = np.exp(log_scales)
    opacity = 1.0 / (1.0 + np.exp(-logits))
    log_ratio = np.log(opacity / np.float32(alpha_min))
    proj, radii, rect = project_forward(
        means, quats, scales, opacity, log_ratio, colors, viewmat, intr, lims, width, height,
        tile, near, far, eps2d, sigma_extent,
    )  # fmt: skip
    return Projected(proj, radii, rect, scales, opacity, intr, lims)


def frustum_limits(intr: np.ndarray, width: int, height: int) -> np.ndarray:
    """(lim_x-, lim_x+, lim_y-, lim_y+) tangent limits for the EWA Jacobian, see module doc."""
    fx, fy, cx, cy = (float(v) for v in intr)
    return np.array(
        [
            (cx + 0.5) / fx + 0.3 * width / (2 * fx),
            (width - 0.5 - cx) / fx + 0.3 * width / (2 * fx),
            (cy + 0.5) / fy + 0.3 * height / (2 * fy),
            (height - 0.5 - cy) / fy + 0.3 * height / (2 * fy),
        ]
    )
