"""One choice of Numba's threading layer for every package with parallel kernels.

Numba's default picks TBB when it finds it; the TBB in some images is too old for Numba (it warns
on first use) and TBB clashes with the one torch and open3d load. OpenMP is thread-safe and
present wherever gcc's runtime is. Call ``use_openmp_threads()`` before compiling or launching a
parallel kernel (sim, calibration and reconstructor do, at import). A ``NUMBA_THREADING_LAYER``
set by the user wins. This module does not import Numba.
"""

from __future__ import annotations

import os
import sys

LAYER = "omp"


def use_openmp_threads() -> None:
    if "NUMBA_THREADING_LAYER" in os.environ:
        return
    os.environ["NUMBA_THREADING_LAYER"] = LAYER
    numba = sys.modules.get("numba")
    if numba is not None:  # imported already: its config has read the environment
        numba.config.THREADING_LAYER = LAYER
