"""Numba kernels of the wand detector (``calibration.detect.detector``), each the fast twin of
slow, obvious code in ``calibration.detect._reference``.

The detector's per-sphere work is many operations on arrays of a few hundred values: on 3-5 px
spheres, many small float32 array operations cost more in numpy's per-call overhead than in
arithmetic. These kernels do the same maths in float64 loops. Each is the fast twin of code in
``calibration.detect._reference`` (the names below, and in the kernels' docstrings, are that
module's), which ``DetectorConfig(kernels="numpy")`` runs:

  _bilinear_nb, edge_points_nb   <-> bilinear, edge_points (with _coverage and _coverage_map):
                                     rays, bilinear samples, unmixing and the edge crossing in
                                     one pass
  robust_cone_nb                 <-> robust_fit ("sphere" method)
  ellipse_through_nb             <-> ellipse_through
  _lstsq_nb, _median_nb, _smallest_right_singular_vector_nb <-> np.linalg.lstsq, np.median,
                                     np.linalg.svd (LAPACK in numba compiles slowly)
  moving_nb, colour_where_nb     <-> candidate_mask (cv2): the spheres' colour tested only
                                     near pixels that differ from the background, by a table of
                                     cv2's own HSV test (colour_table, plain Python)

tests/calibration/test_detect_kernels.py checks each pair against the other: the same edge
points to 1e-4 px (1e-6 on the simulator), the same masks bit for bit. bench/bench_wand_detect.py
compares the two on simulated sessions (about 3x). The kernels compile on first use (about 10 s
per process) and are cached next to this file (``cache=True``), so later processes load them in
well under a second.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numba import njit


@functools.lru_cache(maxsize=8)
def colour_table(
    bounds: tuple[tuple[int, int, int], tuple[int, int, int]],
) -> np.ndarray:
    """``config.colour_mask``'s verdict on every BGR colour, one bit each (2 MB): bit
    ``(b << 16) | (g << 8) | r``, little-endian within bytes. Made by ``cv2`` itself (HSV
    conversion and ``inRange``), so a look-up is exactly what the reference computes."""
    lo, hi = (np.array(v, np.uint8) for v in bounds)
    levels = np.arange(256, dtype=np.uint8)
    gr = np.empty((16, 256, 256, 3), np.uint8)
    gr[..., 1] = levels[None, :, None]
    gr[..., 2] = levels[None, None, :]
    bits = np.empty(1 << 24, np.bool_)
    for b0 in range(0, 256, 16):
        gr[..., 0] = np.arange(b0, b0 + 16, dtype=np.uint8)[:, None, None]
        hsv = cv2.cvtColor(gr.reshape(16 * 256, 256, 3), cv2.COLOR_BGR2HSV)
        bits[b0 << 16 : (b0 + 16) << 16] = cv2.inRange(hsv, lo, hi).reshape(-1) > 0
    return np.packbits(bits, bitorder="little")


@njit(cache=True, error_model="numpy")
def _bilinear_setup(x: float, y: float, h: int, w: int) -> tuple[int, int, float, float, bool]:
    """Top-left pixel, fractions and inside flag of a bilinear sample, as ``bilinear``."""
    inside = x >= 0.0 and y >= 0.0 and x <= w - 1 and y <= h - 1
    xc = min(max(x, 0.0), w - 1.001)
    yc = min(max(y, 0.0), h - 1.001)
    x0 = int(xc)
    y0 = int(yc)
    return x0, y0, xc - x0, yc - y0, inside


@njit(cache=True, error_model="numpy")
def _at_least(v: int, level: int) -> float:
    return 1.0 if v >= level else 0.0


@njit(cache=True, error_model="numpy")
def _lerp4(v00: float, v01: float, v10: float, v11: float, fx: float, fy: float) -> float:
    top = v00 + (v01 - v00) * fx
    bot = v10 + (v11 - v10) * fx
    return top + (bot - top) * fy


@njit(cache=True, error_model="numpy")
def _bilinear_nb(img: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``bilinear`` (in float64): samples (N, C) of (h, w, C) ``img`` at (N, 2) (x, y)."""
    h, w, nc = img.shape
    n = pts.shape[0]
    out = np.empty((n, nc))
    inside = np.empty(n, np.bool_)
    for i in range(n):
        x0, y0, fx, fy, ins = _bilinear_setup(pts[i, 0], pts[i, 1], h, w)
        inside[i] = ins
        for k in range(nc):
            out[i, k] = _lerp4(
                img[y0, x0, k],
                img[y0, x0 + 1, k],
                img[y0 + 1, x0, k],
                img[y0 + 1, x0 + 1, k],
                fx,
                fy,
            )
    return out, inside


@njit(cache=True, error_model="numpy")
def _cover_px(
    roi: np.ndarray, bg: np.ndarray, lut: np.ndarray, y: int, x: int, P: np.ndarray, c2: float
) -> float:
    """``_coverage_map`` at one pixel: NaN where the background cannot tell."""
    pi0 = pi1 = pi2 = pb0 = pb1 = pb2 = 0.0
    for k in range(3):
        li = lut[roi[y, x, k]]
        lb = lut[bg[y, x, k]]
        pi0 += li * P[k, 0]
        pi1 += li * P[k, 1]
        pi2 += li * P[k, 2]
        pb0 += lb * P[k, 0]
        pb1 += lb * P[k, 1]
        pb2 += lb * P[k, 2]
    nb = pb0 * pb0 + pb1 * pb1 + pb2 * pb2
    if nb < c2:
        return np.nan
    return 1.0 - (pi0 * pb0 + pi1 * pb1 + pi2 * pb2) / max(nb, 1e-12)


@njit(cache=True, error_model="numpy")
def edge_points_nb(  # noqa: C901, PLR0912, PLR0915
    roi: np.ndarray,
    bg: np.ndarray,
    has_bg: bool,
    lut: np.ndarray,
    rho3: np.ndarray,
    c: np.ndarray,
    A: np.ndarray,
    rays_per_px: float,
    max_rays: int,
    off: np.ndarray,
    step: float,
    clip_level: int,
    min_contrast: float,
) -> tuple[np.ndarray, int]:
    """``edge_points`` (with ``_coverage``) in one pass over the rays."""
    h, w = roi.shape[0], roi.shape[1]
    n_off = off.shape[0]
    # the rays: as many as the expected outline's mean radius asks for
    a00, a01, a10, a11 = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
    half_tr = 0.5 * (a00 + a11)
    disc = math.sqrt(0.25 * (a00 - a11) ** 2 + a10 * a10)
    r_mean = 0.5 * (
        1.0 / math.sqrt(max(half_tr - disc, 1e-9)) + 1.0 / math.sqrt(max(half_tr + disc, 1e-9))
    )
    if not 0.0 < r_mean < 1e6:  # A is positive definite wherever refine makes it
        return np.empty((0, 2)), 16
    n_rays = int(min(max(np.rint(rays_per_px * 2 * math.pi * r_mean), 16.0), max_rays))
    thr = 0.5 - 1.0 / (24.0 * max(r_mean, 1.0))
    c2 = min_contrast * min_contrast
    edges = np.empty((n_rays, 2))
    n_edges = 0
    vals = np.empty((n_off, 3))
    bgv = np.empty((n_off, 3))
    cover = np.empty(n_off)
    prof = np.empty(n_off)
    xs = np.empty(n_off)
    ys = np.empty(n_off)
    P = np.empty((3, 3))
    sph = np.empty(3)
    usable = np.empty(3, np.bool_)
    q4 = np.empty(4)
    # each pixel's coverage against its background, per pattern of usable channels, computed
    # when a ray first needs it (rays share pixels; most rays use all three channels)
    cmaps = np.empty((8, h, w) if has_bg else (1, 1, 1))
    done = np.zeros((8, h, w) if has_bg else (1, 1, 1), np.bool_)
    for r in range(n_rays):
        ang = (r + 0.5) * (2 * math.pi / n_rays)
        dx, dy = math.cos(ang), math.sin(ang)
        rho = 1.0 / math.sqrt((dx * a00 + dy * a10) * dx + (dx * a01 + dy * a11) * dy)
        for k in range(3):
            usable[k] = True
        all_inside = True
        for s in range(n_off):
            t = max(rho + off[s], 0.0)
            xs[s] = c[0] + t * dx
            ys[s] = c[1] + t * dy
            x0, y0, fx, fy, ins = _bilinear_setup(xs[s], ys[s], h, w)
            in_window = -2.0 <= off[s] <= 3.0
            if in_window and not ins:
                all_inside = False
            for k in range(3):
                q00, q01 = roi[y0, x0, k], roi[y0, x0 + 1, k]
                q10, q11 = roi[y0 + 1, x0, k], roi[y0 + 1, x0 + 1, k]
                vals[s, k] = _lerp4(lut[q00], lut[q01], lut[q10], lut[q11], fx, fy)
                if in_window:  # a clipped pixel that carries weight taints the sample
                    clip = _lerp4(
                        _at_least(q00, clip_level),
                        _at_least(q01, clip_level),
                        _at_least(q10, clip_level),
                        _at_least(q11, clip_level),
                        fx,
                        fy,
                    )
                    if clip > 0:
                        usable[k] = False
                if has_bg:
                    b00, b01 = bg[y0, x0, k], bg[y0, x0 + 1, k]
                    b10, b11 = bg[y0 + 1, x0, k], bg[y0 + 1, x0 + 1, k]
                    bgv[s, k] = _lerp4(lut[b00], lut[b01], lut[b10], lut[b11], fx, fy)
                    if in_window:
                        clip = _lerp4(
                            _at_least(b00, clip_level),
                            _at_least(b01, clip_level),
                            _at_least(b10, clip_level),
                            _at_least(b11, clip_level),
                            fx,
                            fy,
                        )
                        if clip > 0:
                            usable[k] = False
        # project the sphere's colour out of the usable channels
        n_usable = 0
        norm = 0.0
        for k in range(3):
            sph[k] = rho3[k] if usable[k] else 0.0
            norm += sph[k] * sph[k]
            n_usable += usable[k]
        norm = max(math.sqrt(norm), 1e-12)
        for k in range(3):
            sph[k] /= norm
        for i in range(3):
            for k in range(3):
                P[i, k] = (1.0 if (i == k and usable[i]) else 0.0) - sph[i] * sph[k]
        # the background just beyond the edge
        B0 = B1 = B2 = 0.0
        n_out = 0
        for s in range(n_off):
            if off[s] >= 2.0:
                B0 += vals[s, 0]
                B1 += vals[s, 1]
                B2 += vals[s, 2]
                n_out += 1
        B0, B1, B2 = B0 / n_out, B1 / n_out, B2 / n_out
        PB0 = P[0, 0] * B0 + P[0, 1] * B1 + P[0, 2] * B2
        PB1 = P[1, 0] * B0 + P[1, 1] * B1 + P[1, 2] * B2
        PB2 = P[2, 0] * B0 + P[2, 1] * B1 + P[2, 2] * B2
        pb2 = PB0 * PB0 + PB1 * PB1 + PB2 * PB2
        den = max(pb2, 1e-12)
        for s in range(n_off):
            cover[s] = 1.0 - (vals[s, 0] * PB0 + vals[s, 1] * PB1 + vals[s, 2] * PB2) / den
        ok = math.sqrt(pb2) >= min_contrast
        if has_bg and n_usable >= 2:
            dev = 0.0
            for s in range(n_off):
                if off[s] >= 2.0:
                    m = 0.0
                    for k in range(3):
                        m = max(m, abs(vals[s, k] - bgv[s, k]))
                    dev += m
            dev /= n_out
            if dev <= 0.015 + 0.08 * max(B0, B1, B2):
                # unmix each pixel against its own background, interpolate the coverage
                good = True
                code = usable[0] + 2 * usable[1] + 4 * usable[2]
                for s in range(n_off):
                    x0, y0, fx, fy, _ = _bilinear_setup(xs[s], ys[s], h, w)
                    for corner in range(4):
                        yy, xx = y0 + (corner >> 1), x0 + (corner & 1)
                        if not done[code, yy, xx]:
                            cmaps[code, yy, xx] = _cover_px(roi, bg, lut, yy, xx, P, c2)
                            done[code, yy, xx] = True
                        q4[corner] = cmaps[code, yy, xx]
                    v = _lerp4(q4[0], q4[1], q4[2], q4[3], fx, fy)
                    if -2.0 <= off[s] <= 3.0 and not math.isfinite(v):
                        good = False
                        break
                    prof[s] = v
                if good:
                    for s in range(n_off):
                        cover[s] = prof[s]
                    ok = True
        if not ok or n_usable < 2 or not all_inside:
            continue
        # the crossing of the threshold nearest the expected edge
        j = -1
        best = np.inf
        for s in range(n_off - 1):
            if cover[s] >= thr and not cover[s + 1] >= thr:
                d = abs(0.5 * (off[s] + off[s + 1]))
                if d < best:
                    best = d
                    j = s
        if j < 0:
            continue
        o_edge = off[j] + step * (cover[j] - thr) / max(cover[j] - cover[j + 1], 1e-9)
        if not abs(o_edge) <= 2.0 or not rho + o_edge > 0.5:
            continue
        # the profile must look like an edge: the sphere just inside it
        in_sum = 0.0
        n_in = 0
        for s in range(n_off):
            if o_edge - 1.5 <= off[s] <= o_edge - 1.0:
                in_sum += cover[s]
                n_in += 1
        if n_in == 0 or not in_sum / n_in >= 0.75:
            continue
        edges[n_edges, 0] = c[0] + (rho + o_edge) * dx
        edges[n_edges, 1] = c[1] + (rho + o_edge) * dy
        n_edges += 1
    return edges[:n_edges].copy(), n_rays


@njit(cache=True, error_model="numpy")
def _lstsq_nb(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares solution of ``M x = b`` ((N, K), N >= K, full rank) by Householder QR:
    as accurate as ``np.linalg.lstsq``, without LAPACK (which numba compiles slowly)."""
    n, k = M.shape
    R = M.copy()
    y = b.copy()
    v = np.empty(n)
    for j in range(k):
        norm = 0.0
        for i in range(j, n):
            norm += R[i, j] * R[i, j]
        norm = math.sqrt(norm)
        if norm == 0.0:
            continue
        alpha = -norm if R[j, j] > 0 else norm
        vv = 0.0
        for i in range(j, n):
            v[i] = R[i, j]
        v[j] -= alpha
        for i in range(j, n):
            vv += v[i] * v[i]
        if vv == 0.0:
            continue
        for jj in range(j, k):
            d = 0.0
            for i in range(j, n):
                d += v[i] * R[i, jj]
            d *= 2.0 / vv
            for i in range(j, n):
                R[i, jj] -= d * v[i]
        d = 0.0
        for i in range(j, n):
            d += v[i] * y[i]
        d *= 2.0 / vv
        for i in range(j, n):
            y[i] -= d * v[i]
    x = np.zeros(k)
    for j in range(k - 1, -1, -1):
        t = y[j]
        for jj in range(j + 1, k):
            t -= R[j, jj] * x[jj]
        x[j] = t / R[j, j]
    return x


@njit(cache=True, error_model="numpy")
def _median_nb(values: np.ndarray) -> float:
    """``np.median`` of a short 1-D array (insertion sort of a copy)."""
    a = values.copy()
    n = a.shape[0]
    for i in range(1, n):
        t = a[i]
        j = i - 1
        while j >= 0 and a[j] > t:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = t
    if n % 2:
        return float(a[n // 2])
    return 0.5 * (a[n // 2 - 1] + a[n // 2])


@njit(cache=True, error_model="numpy")
def _smallest_right_singular_vector_nb(M: np.ndarray) -> np.ndarray:
    """Unit vector ``v`` minimising ``|M v|`` for (N, K) ``M``: one-sided Jacobi SVD (rotate
    pairs of columns until all are orthogonal; the rotations make ``V``), then the column of
    least norm. Accurate to rounding, like LAPACK's SVD, and quick to compile."""
    n, k = M.shape
    W = M.copy()
    V = np.zeros((k, k))
    for i in range(k):
        V[i, i] = 1.0
    for _ in range(60):
        off = 0.0
        for p in range(k - 1):
            for q in range(p + 1, k):
                alpha = beta = gamma = 0.0
                for i in range(n):
                    alpha += W[i, p] * W[i, p]
                    beta += W[i, q] * W[i, q]
                    gamma += W[i, p] * W[i, q]
                if gamma == 0.0:
                    continue
                off = max(off, abs(gamma) / math.sqrt(alpha * beta))
                zeta = (beta - alpha) / (2.0 * gamma)
                t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                sn = c * t
                for i in range(n):
                    wp, wq = W[i, p], W[i, q]
                    W[i, p] = c * wp - sn * wq
                    W[i, q] = sn * wp + c * wq
                for i in range(k):
                    vp, vq = V[i, p], V[i, q]
                    V[i, p] = c * vp - sn * vq
                    V[i, q] = sn * vp + c * vq
        if off < 1e-15:
            break
    best, j_min = np.inf, 0
    for j in range(k):
        norm = 0.0
        for i in range(n):
            norm += W[i, j] * W[i, j]
        if norm < best:
            best, j_min = norm, j
    return V[:, j_min].copy()


@njit(cache=True, error_model="numpy")
def robust_cone_nb(
    xy: np.ndarray, focal_px: float
) -> tuple[bool, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """``robust_fit`` for ``centre_method="sphere"``: (ok, axis, sin_alpha, rays,
    residuals_px, keep) from (N, 2) normalized edge points."""
    n = xy.shape[0]
    U = np.empty((n, 3))
    for i in range(n):
        s = math.sqrt(xy[i, 0] ** 2 + xy[i, 1] ** 2 + 1.0)
        U[i, 0] = xy[i, 0] / s
        U[i, 1] = xy[i, 1] / s
        U[i, 2] = 1.0 / s
    keep = np.ones(n, np.bool_)
    axis: np.ndarray = np.zeros(3)
    sin_alpha = np.nan
    res = np.zeros(n)
    for _ in range(3):
        n_keep = 0
        for i in range(n):
            n_keep += keep[i]
        if n_keep < 6:
            return False, axis, sin_alpha, U, res, keep
        Uk = np.empty((n_keep, 3))
        m = 0
        for i in range(n):
            if keep[i]:
                Uk[m, 0], Uk[m, 1], Uk[m, 2] = U[i, 0], U[i, 1], U[i, 2]
                m += 1
        wv = _lstsq_nb(Uk, np.ones(n_keep))
        norm = math.sqrt(wv[0] ** 2 + wv[1] ** 2 + wv[2] ** 2)
        sign = -1.0 if wv[2] < 0 else 1.0
        axis = np.empty(3)
        for k in range(3):
            axis[k] = sign * wv[k] / norm
        if not norm > 1.0:
            return False, axis, np.nan, U, res, keep
        sin_alpha = math.sqrt(max(1.0 - 1.0 / (norm * norm), 0.0))
        alpha = math.asin(min(max(sin_alpha, 0.0), 1.0))
        absr = np.empty(n_keep)
        m = 0
        for i in range(n):
            d = U[i, 0] * axis[0] + U[i, 1] * axis[1] + U[i, 2] * axis[2]
            res[i] = (math.acos(min(max(d, -1.0), 1.0)) - alpha) * focal_px
            if keep[i]:
                absr[m] = abs(res[i])
                m += 1
        tol = max(4.0 * 1.4826 * _median_nb(absr), 0.2)
        changed = False
        new_keep = np.empty(n, np.bool_)
        for i in range(n):
            new_keep[i] = abs(res[i]) <= tol
            changed |= new_keep[i] != keep[i]
        if not changed:
            break
        keep = new_keep
    return True, axis, sin_alpha, U, res, keep


@njit(cache=True, error_model="numpy")
def ellipse_through_nb(points: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:
    """``ellipse_through``: (ok, centre (2,), shape A (2, 2)) of the conic through (N, 2) px."""
    centre = np.zeros(2)
    A = np.zeros((2, 2))
    n = points.shape[0]
    if n < 5:
        return False, centre, A
    mx = my = 0.0
    for i in range(n):
        mx += points[i, 0]
        my += points[i, 1]
    mx /= n
    my /= n
    spread = 0.0
    for i in range(n):
        spread += math.sqrt((points[i, 0] - mx) ** 2 + (points[i, 1] - my) ** 2)
    s = math.sqrt(2.0) / max(spread / n, 1e-12)
    M = np.empty((n, 6))
    for i in range(n):
        x = (points[i, 0] - mx) * s
        y = (points[i, 1] - my) * s
        M[i, 0] = x * x
        M[i, 1] = x * y
        M[i, 2] = y * y
        M[i, 3] = x
        M[i, 4] = y
        M[i, 5] = 1.0
    v = _smallest_right_singular_vector_nb(M)  # a x^2 + b xy + c y^2 + d x + e y + f = 0
    Cs = np.empty((3, 3))
    Cs[0, 0], Cs[1, 1], Cs[2, 2] = v[0], v[2], v[5]
    Cs[0, 1] = Cs[1, 0] = v[1] / 2
    Cs[0, 2] = Cs[2, 0] = v[3] / 2
    Cs[1, 2] = Cs[2, 1] = v[4] / 2
    T = np.zeros((3, 3))  # from pixels to the centred, scaled points
    T[0, 0] = T[1, 1] = s
    T[0, 2], T[1, 2], T[2, 2] = -s * mx, -s * my, 1.0
    C = np.zeros((3, 3))  # C = T^T Cs T
    norm = 0.0
    for i in range(3):  # loops: numba compiles ``@`` (BLAS) slowly
        for j in range(3):
            for p in range(3):
                for q in range(3):
                    C[i, j] += T[p, i] * Cs[p, q] * T[q, j]
            norm += C[i, j] * C[i, j]
    norm = math.sqrt(norm)
    for i in range(3):
        for j in range(3):
            C[i, j] /= norm
    det = C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]
    if det == 0.0 or not math.isfinite(det):
        return False, centre, A
    centre[0] = (-C[0, 2] * C[1, 1] + C[1, 2] * C[0, 1]) / det
    centre[1] = (-C[1, 2] * C[0, 0] + C[0, 2] * C[1, 0]) / det
    k = (
        centre[0] * (C[0, 0] * centre[0] + C[0, 1] * centre[1])
        + centre[1] * (C[1, 0] * centre[0] + C[1, 1] * centre[1])
        - C[2, 2]
    )
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = C[0, 0] / k, C[0, 1] / k, C[1, 0] / k, C[1, 1] / k
    for i in range(2):
        for j in range(2):
            if not math.isfinite(A[i, j]):
                return False, centre, A
    half_tr = 0.5 * (A[0, 0] + A[1, 1])
    lo = half_tr - math.sqrt(0.25 * (A[0, 0] - A[1, 1]) ** 2 + A[1, 0] ** 2)
    if lo <= 0:
        return False, centre, A
    return True, centre, A


@njit(cache=True, error_model="numpy")
def moving_nb(small: np.ndarray, background: np.ndarray, threshold: int) -> np.ndarray:
    """Flat (h * w) uint8 0/1: some channel of the flat (h * w * 3) frame differs from the
    background by more than ``threshold`` (``cv2.absdiff``, the channels' max, a threshold)."""
    n = small.shape[0] // 3
    out = np.empty(n, np.uint8)
    for i in range(n):  # flat indices: numba vectorises this, not the (y, x, k) version
        d0 = abs(np.int16(small[3 * i]) - np.int16(background[3 * i]))
        d1 = abs(np.int16(small[3 * i + 1]) - np.int16(background[3 * i + 1]))
        d2 = abs(np.int16(small[3 * i + 2]) - np.int16(background[3 * i + 2]))
        m = d0 if d0 > d1 else d1
        m = m if m > d2 else d2
        out[i] = 1 if m > threshold else 0
    return out


@njit(cache=True, error_model="numpy")
def colour_where_nb(small: np.ndarray, where: np.ndarray, colour_bits: np.ndarray) -> np.ndarray:
    """Flat (h * w) uint8 0/1: ``config.colour_mask`` of the flat (h * w * 3) frame, looked up in
    ``colour_table``, only where ``where`` (flat (h * w)) is set; 0 elsewhere."""
    n = where.shape[0]
    out = np.zeros(n, np.uint8)
    words = where[: n - n % 8].view(np.uint64)  # skip eight clear bytes at a time
    for wi in range(words.shape[0] + 1):
        if wi < words.shape[0] and words[wi] == 0:
            continue
        for i in range(8 * wi, min(8 * wi + 8, n)):
            if where[i]:
                idx = (
                    (np.int64(small[3 * i]) << 16)
                    | (np.int64(small[3 * i + 1]) << 8)
                    | np.int64(small[3 * i + 2])
                )
                out[i] = (colour_bits[idx >> 3] >> (idx & 7)) & 1
    return out
