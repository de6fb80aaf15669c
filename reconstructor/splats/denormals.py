"""Float32 denormals flushed to zero on every thread that trains.

The Gaussians that fade below alpha_min get no more gradient, and their Adam moments decay by
beta each step into the denormal range (below 1.2e-38), where x86 arithmetic is 10-20x slower.
The second moment never leaves it: 0.999 times the smallest denormal rounds back to itself.
Measured on the trained 193k-Gaussian model: Adam took 3.7 ms a step, then 20-26 ms from about
600 steps after its Gaussians stopped getting gradients; with the flush, 2.6-3.1 ms throughout.
A denormal moment moves a parameter by nothing either way, so the flush changes no result that
matters.

The flush is a per-thread CPU mode (MXCSR's flush-to-zero and denormals-are-zero bits) and
``torch.set_flush_denormal`` sets it on the calling thread only. A thread copies the mode of the
thread that starts it, so the mode must be set before torch (or Numba) starts its worker
threads, at their first parallel operation: importing ``reconstructor`` does that
(``reconstructor/__init__.py``). Set later, in the trainer, it reached only the main thread, and
Adam still took 29.9 ms a step after the 2000-step schedule (BENCHMARKS.md, "Reconstruction
schedule").
"""

from __future__ import annotations

import torch

_PROBE_ELEMENTS = 1 << 20  # many times torch's parallel grain: every worker thread gets a part
_DENORMAL_BITS = 1 << 20  # float32 bits 0x00100000: 1.5e-39, a denormal


def flush_denormals() -> bool:
    """Set flush-to-zero on the calling thread and on the threads it starts from now on; False
    on a CPU without the mode (torch supports it on x86 only), where nothing changes."""
    return bool(torch.set_flush_denormal(True))


def denormals_flushed_on_all_threads() -> bool:
    """Whether a parallel float32 operation flushes denormals on every torch worker thread.

    Starts torch's worker threads if they have not started (they then copy this thread's mode).
    """
    # made from bits: a float constant would pass through this thread's flush on the way in
    tiny = torch.full((_PROBE_ELEMENTS,), _DENORMAL_BITS, dtype=torch.int32).view(torch.float32)
    return not bool(torch.count_nonzero(tiny * 0.5))
