"""glibc malloc settings for benchmarks that time PyTorch code on this VM."""

from __future__ import annotations

import ctypes


def tune_malloc() -> bool:
    """Keep freed memory in glibc's heap instead of returning it to the kernel.

    On this VM every page handed back and touched again costs a page fault of several
    microseconds, which dominates code that makes many large short-lived tensors (a PyTorch
    twin: 2-7x slower with the default settings) and barely moves the numba paths. A
    long-running trainer would set MALLOC_MMAP_THRESHOLD_/MALLOC_TRIM_THRESHOLD_ the same way.
    Returns whether glibc took the settings.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(libc.mallopt(m_mmap_threshold, 1 << 30) and libc.mallopt(m_trim_threshold, 1 << 31))
