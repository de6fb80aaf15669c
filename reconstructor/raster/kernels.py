"""Tile binning and the per-tile compositing kernels, forward and backward (numba).

Both raster kernels run one tile per iteration of a ``prange`` (one thread owns a tile, so
per-pixel state needs no locks) and walk the tile's Gaussians in depth order. A Gaussian only
visits the rows of the tile where its alpha can reach ``alpha_min`` (the vertical extent of
``dᵀ conic d <= 2 ln(opacity / alpha_min)``, widened a little; the exact per-pixel test decides
inside), and within those rows every pixel, in one flat loop that LLVM vectorises (8 lanes of
AVX2). Vectorising needs: branch-free bodies (selects, not ``continue``), an ``exp`` that
inlines (``exp_neg``, below), 32-bit lanes only, unsigned indices (numba adds a wraparound
select for signed ones), and all per-tile pixel state in ONE float32 buffer whose fields sit
at compile-time-constant offsets, so LLVM can prove they do not overlap without runtime checks.
Each pixel still sees its fragments front to back in list order, so the sums are the same as
the obvious per-pixel loop.

The backward pass walks each tile's list back to front from the last fragment any pixel used,
recovering each fragment's transmittance as ``T_before = T_after / (1 - alpha)`` from the
stored final transmittance, and the colour behind it by the recursion
``B_before = alpha c + (1 - alpha) B_after`` starting from the background. Each (tile,
Gaussian) pair writes its summed gradient to its own row of a record array (race-free);
``projection.project_backward`` adds each Gaussian's rows in a fixed order (deterministic).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange
from numba.core import types
from numba.extending import intrinsic

from reconstructor.raster.projection import (
    CA,
    CB,
    CB_,
    CC,
    CG,
    CR,
    DEPTH,
    HX,
    HY,
    MX,
    MY,
    OPA,
    PROJ_COLS,
)  # fmt: skip

N_RECORD = 9  # dL/d(mean2d x, y, conic a, b, c, opacity, r, g, b) per (tile, Gaussian) pair
_RADIX_BITS = 11
_ALPHA_DEPTH_MIN = 1e-3  # below this pixel alpha the depth output is 0
MAX_TILE_PX = 32
_LANES = 8  # columns per lane block: one AVX2 vector of float32
# Per-tile pixel state: field k of buffer index i at buffer[k * _FIELD + i]
_FIELD = MAX_TILE_PX * MAX_TILE_PX


@njit(cache=True)
def _visible_by_depth(depth_bits, radii):
    """Indices (int32) of the Gaussians with radii > 0, front to back, ties by index."""
    n = radii.shape[0]
    nvis = 0
    for i in range(n):
        nvis += radii[i] > 0
    idx = np.empty(nvis, np.int32)
    keys = np.empty(nvis, np.uint32)
    k = 0
    for i in range(n):
        if radii[i] > 0:
            idx[k] = i
            keys[k] = depth_bits[i]
            k += 1
    # Stable LSD radix sort on the depth bits: ties keep index order, like a stable argsort.
    idx2 = np.empty_like(idx)
    keys2 = np.empty_like(keys)
    n_buckets = 1 << _RADIX_BITS
    mask = np.uint32(n_buckets - 1)
    counts = np.empty(n_buckets + 1, np.int64)
    for shift in range(0, 32, _RADIX_BITS):
        counts[:] = 0
        for k in range(nvis):
            counts[((keys[k] >> np.uint32(shift)) & mask) + 1] += 1
        for b in range(n_buckets):
            counts[b + 1] += counts[b]
        for k in range(nvis):
            d = (keys[k] >> np.uint32(shift)) & mask
            pos = counts[d]
            counts[d] = pos + 1
            idx2[pos] = idx[k]
            keys2[pos] = keys[k]
        idx, idx2 = idx2, idx
        keys, keys2 = keys2, keys
    return idx


@njit(cache=True)
def bin_gaussians(depth_bits, radii, rect, ntx, n_tiles):
    """Sort the visible Gaussians by depth and list them per tile.

    Args: depth_bits (N,) uint32, the bits of the positive float32 camera depths (monotone in
    the depth); radii (N,) int32 (0 = culled); rect (N, 4) int32 inclusive tile rectangles
    (x0, x1, y0, y1); ntx tiles per row; n_tiles in total. Serial: in parallel it was no
    faster on two cores and took seconds longer to compile.

    Returns: pairs (M,) int32 Gaussian index of every (tile, Gaussian) pair, grouped by tile
    and front to back within a tile (ties by index); offsets (n_tiles + 1,) int64 so that tile
    t owns ``pairs[offsets[t]:offsets[t + 1]]``; slots (M,) int64 and goffsets (N + 1,) int64:
    the pairs renumbered Gaussian by Gaussian, pair j being number slots[j] and Gaussian i owning
    numbers goffsets[i]..goffsets[i + 1] - 1 (none if culled). The backward pass stores each
    pair's gradient under its slot so that a Gaussian's gradients are adjacent in memory.
    """
    n = radii.shape[0]
    goffsets = np.empty(n + 1, np.int64)
    goffsets[0] = 0
    for i in range(n):
        covered = 0
        if radii[i] > 0:
            covered = (rect[i, 1] - rect[i, 0] + 1) * (rect[i, 3] - rect[i, 2] + 1)
        goffsets[i + 1] = goffsets[i] + covered
    idx = _visible_by_depth(depth_bits, radii)
    nvis = idx.shape[0]
    # Counting sort by tile: filling in depth order keeps each tile's list depth-sorted.
    offsets = np.zeros(n_tiles + 1, np.int64)
    for k in range(nvis):
        g = idx[k]
        for ty in range(rect[g, 2], rect[g, 3] + 1):
            for tx in range(rect[g, 0], rect[g, 1] + 1):
                offsets[ty * ntx + tx + 1] += 1
    for t in range(n_tiles):
        offsets[t + 1] += offsets[t]
    cursor = offsets[:-1].copy()
    pairs = np.empty(offsets[n_tiles], np.int32)
    slots = np.empty(offsets[n_tiles], np.int64)
    for k in range(nvis):
        g = idx[k]
        m = goffsets[g]
        for ty in range(rect[g, 2], rect[g, 3] + 1):
            for tx in range(rect[g, 0], rect[g, 1] + 1):
                pos = cursor[ty * ntx + tx]
                cursor[ty * ntx + tx] = pos + 1
                pairs[pos] = g
                slots[pos] = m
                m += 1
    return pairs, offsets, slots, goffsets


# exp(x) for x <= 0 in float32, inlinable and vectorisable (libm's expf is neither): Cody-Waite
# reduction x = r + k ln2, a degree-7 Taylor polynomial for exp(r), |r| <= ln2 / 2, and 2^k
# built from its exponent bits. Within 1.2e-7 relative of exp on [-20, 0].
_LOG2E = np.float32(1.4426950408889634)
_LN2 = np.float32(0.6931471805599453)


@intrinsic
def _pow2(typingctx, k):
    """2**k for an integer-valued float32 k in [-126, 127], from the exponent bits."""
    if k != types.float32:
        return None

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        bits = builder.add(builder.fptosi(args[0], i32), ir.Constant(i32, 127))
        return builder.bitcast(builder.shl(bits, ir.Constant(i32, 23)), ir.FloatType())

    return types.float32(types.float32), codegen


@njit(cache=True, fastmath=True)
def exp_neg(x):
    """exp(x) for float32 x, clamped to [-87, 0]."""
    x = min(max(x, np.float32(-87.0)), np.float32(0.0))
    k = np.floor(x * _LOG2E + np.float32(0.5))
    r = x - k * _LN2
    p = np.float32(1.0 / 5040.0)
    p = p * r + np.float32(1.0 / 720.0)
    p = p * r + np.float32(1.0 / 120.0)
    p = p * r + np.float32(1.0 / 24.0)
    p = p * r + np.float32(1.0 / 6.0)
    p = p * r + np.float32(0.5)
    p = p * r + np.float32(1.0)
    p = p * r + np.float32(1.0)
    return p * _pow2(k)  # type: ignore[call-arg]


@njit(cache=True, fastmath=True)
def _tile_box(t, ntx, tile, width, height):
    """Pixel box (x0, y0, x1, y1), inclusive, of tile t."""
    x0 = (t % ntx) * tile
    y0 = (t // ntx) * tile
    return x0, y0, min(x0 + tile, width) - 1, min(y0 + tile, height) - 1


@njit(cache=True, fastmath=True)
def _footprint(proj, g, x0, y0, x1, y1):
    """Tile-relative rows r0..r1 and lane blocks b0..b1 (inclusive) where Gaussian g may
    reach alpha_min; r0 > r1 if nowhere."""
    hy = proj[g, HY]
    if hy < 0:
        return 1, 0, 0, -1
    my, mx, hx = proj[g, MY], proj[g, MX], proj[g, HX]
    v0 = max(y0, math.ceil(my - hy))
    v1 = min(y1, math.floor(my + hy))
    u0 = max(x0, math.ceil(mx - hx))
    u1 = min(x1, math.floor(mx + hx))
    if v0 > v1 or u0 > u1:
        return 1, 0, 0, -1
    return v0 - y0, v1 - y0, (u0 - x0) // _LANES, (u1 - x0) // _LANES


@njit(cache=True, fastmath=True)
def _pixel(t_idx, tile):
    """Tile-relative (column, row) of buffer index t_idx: blocks of _LANES columns, row-major
    inside a block, so a block's rows r0..r1 are one contiguous run."""
    bs = tile * _LANES
    blk, rest = t_idx // bs, t_idx % bs
    return blk * _LANES + rest % _LANES, rest // _LANES


@njit(cache=True, fastmath=True)
def _gather_tile(proj, pairs, start, stop, x0, y0, x1, y1):
    """Copy the Gaussians of pairs[start:stop] that can reach a pixel of the tile into a local
    array, in list order: proj rows (K, PROJ_COLS) and (K, 5) int64 (r0, r1, b0, b1, list
    index). The gather's loads are independent, so their cache misses overlap instead of
    stalling the compositing loop one Gaussian at a time."""
    loc = np.empty((stop - start, PROJ_COLS), np.float32)
    fp = np.empty((stop - start, 5), np.int64)
    k = 0
    for j in range(start, stop):
        g = pairs[j]
        r0, r1, b0, b1 = _footprint(proj, g, x0, y0, x1, y1)
        if r0 > r1:
            continue
        for c in range(PROJ_COLS):
            loc[k, c] = proj[g, c]
        fp[k, 0], fp[k, 1], fp[k, 2], fp[k, 3], fp[k, 4] = r0, r1, b0, b1, j - start
        k += 1
    return loc[:k], fp[:k]


@njit(cache=True, fastmath=True)
def _gather_drawn(proj, pairs, drawn, start, stop):
    """Like ``_gather_tile`` for the backward pass: the Gaussians of pairs[start:stop] that drew
    something in the forward pass; returns their proj rows (K, PROJ_COLS) and list indices."""
    loc = np.empty((stop - start, PROJ_COLS), np.float32)
    idx = np.empty(stop - start, np.int64)
    k = 0
    for j in range(start, stop):
        any_drawn = False
        for blk in range(drawn.shape[1]):
            any_drawn |= drawn[j, blk, 0] <= drawn[j, blk, 1]
        if not any_drawn:
            continue
        g = pairs[j]
        for c in range(PROJ_COLS):
            loc[k, c] = proj[g, c]
        idx[k] = j
        k += 1
    return loc[:k], idx[:k]


@njit(cache=True, fastmath=True)
def _drawn_rows(st, base, r0, r1, j_used):
    """First and last of rows r0..r1 of the lane block at ``base`` holding a pixel whose last
    fragment is list entry j_used (first > last if none)."""
    d0, d1 = r1 + 1, r0 - 1
    for r in range(r0, r1 + 1):
        if _row_has(st, base + r * _LANES, j_used):
            d0 = r
            break
    for r in range(r1, d0 - 1, -1):
        if _row_has(st, base + r * _LANES, j_used):
            d1 = r
            break
    return d0, d1


@njit(cache=True, fastmath=True)
def _row_has(st, i0, j_used):
    hit = False
    for i in range(i0, i0 + _LANES):
        hit |= st[_LAST + np.uint64(i)] == j_used
    return hit


# forward state fields
_T, _R, _G, _B, _D, _LAST, _DONE, _X, _Y = (np.uint64(k * _FIELD) for k in range(9))


@njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def raster_forward(proj, pairs, offsets, width, height, tile, ntx, bg, alpha_min, alpha_max, t_min):
    """Composite every tile front to back.

    Args: proj (N, PROJ_COLS) float32 from ``project_forward``; pairs, offsets from
    ``bin_gaussians``; bg (3,) float32; alpha_min, alpha_max, t_min floats; tile <= 32.

    Returns: image (H, W, 3), t_final (H, W), depth (H, W) float32; n_used (H, W) int32, the
    number of entries of the pixel's tile list up to and including its last fragment; drawn
    (M, blocks, 2) int8, for each pair and lane block the first and last tile row where the
    Gaussian drew something (first > last if nowhere), which spares the backward pass the rows
    and Gaussians that drew nothing.
    """
    image = np.empty((height, width, 3), np.float32)
    t_final = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    n_used = np.empty((height, width), np.int32)
    amin, amax, tmin = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    one, zero, half = np.float32(1.0), np.float32(0.0), np.float32(-0.5)
    n_blocks = (tile + _LANES - 1) // _LANES
    bs = tile * _LANES
    drawn = np.empty((pairs.shape[0], n_blocks, 2), np.int8)
    for t in prange(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(t, ntx, tile, width, height)
        for j in range(offsets[t], offsets[t + 1]):
            for blk in range(n_blocks):
                drawn[j, blk, 0], drawn[j, blk, 1] = 1, 0
        st = np.empty(9 * _FIELD, np.float32)
        blk_active = np.empty(n_blocks, np.int64)  # explicit loops, no array expressions:
        for blk in range(n_blocks):  # numba would compile those as nested parallel loops
            blk_active[blk] = 0
        for i in range(n_blocks * bs):
            q = np.uint64(i)
            col, row = _pixel(i, tile)
            inside = col < tile and x0 + col <= x1 and y0 + row <= y1
            blk_active[i // bs] += inside
            st[_T + q], st[_R + q], st[_G + q], st[_B + q], st[_D + q] = one, zero, zero, zero, zero
            st[_LAST + q] = zero
            st[_DONE + q] = zero if inside else one  # lanes past the image edge never draw
            st[_X + q], st[_Y + q] = x0 + col, y0 + row
        active = 0
        for blk in range(n_blocks):
            active += blk_active[blk]
        loc, fp = _gather_tile(proj, pairs, offsets[t], offsets[t + 1], x0, y0, x1, y1)
        for k in range(loc.shape[0]):
            r0, r1, b0, b1 = fp[k, 0], fp[k, 1], fp[k, 2], fp[k, 3]
            mx, my, o = loc[k, MX], loc[k, MY], loc[k, OPA]
            a, b, c = loc[k, CA], loc[k, CB], loc[k, CC]
            cr, cg, cb, z = loc[k, CR], loc[k, CG], loc[k, CB_], loc[k, DEPTH]
            j_used = np.float32(fp[k, 4] + 1)
            j = offsets[t] + fp[k, 4]
            for blk in range(b0, b1 + 1):
                if blk_active[blk] == 0:
                    continue
                n_stop = n_draw = zero
                p0, p1 = blk * bs + r0 * _LANES, blk * bs + (r1 + 1) * _LANES
                for p in range(np.uint64(p0), np.uint64(p1)):
                    dx = st[_X + p] - mx
                    dy = st[_Y + p] - my
                    alpha = min(amax, o * exp_neg(half * (a * dx * dx + c * dy * dy) - b * dx * dy))
                    tr = st[_T + p]
                    test_t = tr * (one - alpha)
                    ok = (alpha >= amin) & (st[_DONE + p] == zero)
                    draw = ok & (test_t >= tmin)
                    stop = ok & (test_t < tmin)  # 3DGS: this fragment is not drawn
                    w = alpha * tr if draw else zero
                    st[_R + p] += w * cr
                    st[_G + p] += w * cg
                    st[_B + p] += w * cb
                    st[_D + p] += w * z
                    st[_T + p] = test_t if draw else tr
                    st[_LAST + p] = j_used if draw else st[_LAST + p]
                    st[_DONE + p] = one if stop else st[_DONE + p]
                    n_stop += one if stop else zero
                    n_draw += one if draw else zero
                # rows this Gaussian drew in: those with a pixel whose last entry is now this one
                # (a scan after the loop: numba's min/max reductions do not vectorise)
                if n_draw > zero:
                    d0, d1 = _drawn_rows(st, blk * bs, r0, r1, j_used)
                    drawn[j, blk, 0], drawn[j, blk, 1] = d0, d1
                blk_active[blk] -= int(n_stop)
                active -= int(n_stop)
            if active == 0:
                break
        for i in range(n_blocks * bs):
            q = np.uint64(i)
            col, row = _pixel(i, tile)
            u, v = x0 + col, y0 + row
            if col >= tile or u > x1 or v > y1:
                continue
            tr = st[_T + q]
            image[v, u, 0] = st[_R + q] + tr * bg[0]
            image[v, u, 1] = st[_G + q] + tr * bg[1]
            image[v, u, 2] = st[_B + q] + tr * bg[2]
            t_final[v, u] = tr
            a_px = one - tr
            depth[v, u] = st[_D + q] / a_px if a_px >= _ALPHA_DEPTH_MIN else zero
            n_used[v, u] = np.int32(st[_LAST + q])
    return image, t_final, depth, n_used, drawn


# backward state fields: transmittance, colour behind (3), dL/dC (3), dL/dalpha_px * T_final
_BT, _BR, _BG, _BB, _GR, _GG, _GB, _GA, _BLAST, _BX, _BY = (
    np.uint64(k * _FIELD) for k in range(11)
)


@njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def raster_backward(
    proj, pairs, offsets, slots, width, height, tile, ntx, bg, alpha_min, alpha_max,
    t_final, n_used, drawn, g_image, g_alpha,
):  # fmt: skip
    """Gradients of the loss per (tile, Gaussian) pair, walking each tile back to front.

    Args: as ``raster_forward`` plus slots from ``bin_gaussians``, the forward's t_final,
    n_used, drawn and the incoming gradients g_image (H, W, 3), g_alpha (H, W) float32.

    Returns: records (M, N_RECORD) float32, pair j's in row slots[j].
    """
    # np.empty, not np.zeros: numba turns np.zeros into a parallel loop, which the small chunk
    # size set for tiles makes very slow; rows past a tile's last fragment are zeroed below.
    records = np.empty((pairs.shape[0], N_RECORD), np.float32)
    amin, amax = np.float32(alpha_min), np.float32(alpha_max)
    one, zero, half = np.float32(1.0), np.float32(0.0), np.float32(-0.5)
    n_blocks = (tile + _LANES - 1) // _LANES
    bs = tile * _LANES
    for t in prange(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(t, ntx, tile, width, height)
        st = np.empty(11 * _FIELD, np.float32)
        for i in range(n_blocks * bs):
            q = np.uint64(i)
            col, row = _pixel(i, tile)
            u, v = x0 + col, y0 + row
            st[_BX + q], st[_BY + q] = u, v
            st[_BR + q], st[_BG + q], st[_BB + q] = bg[0], bg[1], bg[2]
            if col >= tile or u > x1 or v > y1:
                st[_BT + q], st[_BLAST + q] = one, zero
                st[_GR + q], st[_GG + q], st[_GB + q], st[_GA + q] = zero, zero, zero, zero
                continue
            st[_BT + q] = t_final[v, u]
            st[_GR + q], st[_GG + q] = g_image[v, u, 0], g_image[v, u, 1]
            st[_GB + q] = g_image[v, u, 2]
            st[_GA + q] = g_alpha[v, u] * t_final[v, u]
            st[_BLAST + q] = n_used[v, u]
        start, stop = offsets[t], offsets[t + 1]
        loc, idx = _gather_drawn(proj, pairs, drawn, start, stop)
        j_next = stop  # records of pairs that drew nothing here are zero
        for k in range(loc.shape[0] - 1, -1, -1):
            j = idx[k]
            for jz in range(j + 1, j_next):
                for f in range(N_RECORD):
                    records[slots[jz], f] = zero
            j_next = j
            mx, my, o = loc[k, MX], loc[k, MY], loc[k, OPA]
            a, b, c = loc[k, CA], loc[k, CB], loc[k, CC]
            cr, cg, cb = loc[k, CR], loc[k, CG], loc[k, CB_]
            jf = np.float32(j - start)
            g_mx = g_my = g_a = g_b = g_c = g_o = g_r = g_g = g_bl = zero
            for blk in range(n_blocks):
                r0, r1 = drawn[j, blk, 0], drawn[j, blk, 1]
                if r0 > r1:
                    continue
                p0, p1 = blk * bs + r0 * _LANES, blk * bs + (r1 + 1) * _LANES
                for p in range(np.uint64(p0), np.uint64(p1)):
                    dx = st[_BX + p] - mx
                    dy = st[_BY + p] - my
                    gauss = exp_neg(half * (a * dx * dx + c * dy * dy) - b * dx * dy)
                    raw = o * gauss
                    alpha = min(amax, raw)
                    hit = (alpha >= amin) & (jf < st[_BLAST + p])  # drawn in the forward
                    alpha = alpha if hit else zero
                    inv = one / (one - alpha)
                    t_before = st[_BT + p] * inv
                    w = alpha * t_before
                    gc0, gc1, gc2 = st[_GR + p], st[_GG + p], st[_GB + p]
                    b0_, b1_, b2_ = st[_BR + p], st[_BG + p], st[_BB + p]
                    g_r += w * gc0
                    g_g += w * gc1
                    g_bl += w * gc2
                    # dC/dalpha = T (c - B), dalpha_px/dalpha = T_final / (1 - alpha)
                    g_al = st[_GA + p] * inv + t_before * (
                        (cr - b0_) * gc0 + (cg - b1_) * gc1 + (cb - b2_) * gc2
                    )
                    st[_BR + p] = b0_ + alpha * (cr - b0_)
                    st[_BG + p] = b1_ + alpha * (cg - b1_)
                    st[_BB + p] = b2_ + alpha * (cb - b2_)
                    st[_BT + p] = t_before
                    g_al = g_al if hit & (raw <= amax) else zero  # the clamp passes no gradient
                    g_o += gauss * g_al
                    g_pow = raw * g_al
                    g_mx += (a * dx + b * dy) * g_pow
                    g_my += (b * dx + c * dy) * g_pow
                    g_a += half * dx * dx * g_pow
                    g_b -= dx * dy * g_pow
                    g_c += half * dy * dy * g_pow
            rec = records[slots[j]]
            rec[0], rec[1], rec[2], rec[3], rec[4] = g_mx, g_my, g_a, g_b, g_c
            rec[5], rec[6], rec[7], rec[8] = g_o, g_r, g_g, g_bl
        for jz in range(start, j_next):
            for f in range(N_RECORD):
                records[slots[jz], f] = zero
    return records
