"""Background models for wand detection: the per-pixel temporal median of frames spread over a
session (the wand and the operator move, the room mostly does not).

``temporal_median(frames)`` is the fast kernel (numba: a sorting network over the frames, run
on blocks of pixels in parallel); ``temporal_median_reference`` is its slow, obvious twin (numpy's
median). For an odd number of uint8 frames the two are equal bit for bit; for an even number the
median is the mean of the two middle values rounded down (numpy's, then cast to uint8).

Speed (HD1200, 15 frames, one core): numpy's median takes about 2 s per sensor, the kernel about
0.2 s; a rig has 8 sensors.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from protocol.numba_threads import use_openmp_threads

use_openmp_threads()

from numba import njit, prange  # noqa: E402

MAX_FRAMES = 64


def temporal_median(frames: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Per-pixel median of ``frames`` (each (H, W, C) or (H, W) uint8, all the same shape)."""
    stack = _stack(frames)
    n = stack.shape[0]
    flat = stack.reshape(n, -1)
    out = np.empty(flat.shape[1], np.uint8)
    _median_kernel(flat, out)
    return out.reshape(stack.shape[1:])


def temporal_median_reference(frames: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """The same, with numpy (slow): the twin ``temporal_median`` is tested against."""
    return np.median(_stack(frames), axis=0).astype(np.uint8)


def _stack(frames: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    stack = np.asarray(frames) if isinstance(frames, np.ndarray) else np.stack(list(frames))
    if stack.dtype != np.uint8:
        raise ValueError(f"temporal_median needs uint8 frames, got {stack.dtype}")
    if not 1 <= stack.shape[0] <= MAX_FRAMES:
        raise ValueError(f"temporal_median takes 1 to {MAX_FRAMES} frames, got {stack.shape[0]}")
    return np.ascontiguousarray(stack)


@njit(parallel=True, cache=True)
def _median_kernel(flat: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Odd-even transposition sort of each pixel's ``n`` values (n passes of compare-exchanges
    between neighbouring frames), done for a block of pixels at a time so the inner loop runs
    over pixels and vectorises; the middle row is the median."""
    n, m = flat.shape
    block = 2048
    n_blocks = (m + block - 1) // block
    for b in prange(n_blocks):
        start = b * block
        w = min(start + block, m) - start
        buf = np.empty((n, w), np.uint8)
        for i in range(n):
            for j in range(w):
                buf[i, j] = flat[i, start + j]
        for p in range(n):
            for i in range(p % 2, n - 1, 2):
                lo = buf[i]
                hi = buf[i + 1]
                for j in range(w):
                    x = lo[j]
                    y = hi[j]
                    lo[j] = min(x, y)
                    hi[j] = max(x, y)
        h = n // 2
        if n % 2 == 1:
            for j in range(w):
                out[start + j] = buf[h, j]
        else:
            for j in range(w):
                out[start + j] = (np.uint16(buf[h - 1, j]) + np.uint16(buf[h, j])) // 2
