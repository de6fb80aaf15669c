"""Training flushes float32 denormals on every thread: the Adam moments of faded Gaussians decay
into that range, where every operation on them is many times slower
(reconstructor/splats/denormals.py, BENCHMARKS.md, "Reconstruction schedule")."""

from __future__ import annotations

import platform
import subprocess
import sys

import numpy as np
import pytest
import torch

from reconstructor.raster import RasterConfig
from reconstructor.splats.gaussians import init_from_points
from reconstructor.splats.train import TrainConfig, Trainer

# torch supports the flush on x86 only (it returns False elsewhere, e.g. on a Jetson's ARM cores)
pytestmark = pytest.mark.skipif(
    platform.machine().lower() not in ("x86_64", "amd64"),
    reason="torch has no flush-to-zero mode on this CPU",
)

# a parallel float32 product over 4 MB on two torch threads; prints how many results are
# denormals (a thread without flush-to-zero keeps 1.5e-39 * 0.5). The input is made from bits:
# a float constant would be flushed on its way in.
_PROBE = """
import torch
torch.set_num_threads(2)
tiny = torch.full((1 << 20,), 1 << 20, dtype=torch.int32).view(torch.float32)  # 1.5e-39
print("denormal results:", int(torch.count_nonzero(tiny * 0.5)))
"""


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


def test_the_probe_sees_denormals_without_the_flush() -> None:
    out = _run(_PROBE)
    assert out.returncode == 0, out.stderr
    assert "denormal results: 1048576" in out.stdout


def test_every_torch_thread_flushes_denormals_once_reconstructor_is_imported() -> None:
    out = _run("import reconstructor\n" + _PROBE)
    assert out.returncode == 0, out.stderr
    assert "denormal results: 0" in out.stdout


def test_a_trainer_warns_when_torch_threads_started_without_the_flush() -> None:
    code = _PROBE + (
        "import numpy as np\n"
        "from reconstructor.splats.gaussians import init_from_points\n"
        "from reconstructor.raster import RasterConfig\n"
        "from reconstructor.splats.train import TrainConfig, Trainer\n"
        "points = np.random.default_rng(0).uniform(-1, 1, size=(8, 3))\n"
        "gaussians = init_from_points(points, np.full((8, 3), 0.5))\n"
        "Trainer(gaussians, TrainConfig(), RasterConfig(), 1.0)\n"
    )
    out = _run(code)
    assert out.returncode == 0, out.stderr
    assert "denormals are not flushed on torch's worker threads" in out.stderr
    assert "import reconstructor before" in out.stderr


def test_a_trainer_flushes_denormals_on_its_own_thread() -> None:
    tiny = torch.tensor([1e-30], dtype=torch.float32)
    torch.set_flush_denormal(False)
    try:
        assert float(tiny * 1e-9) != 0.0  # a denormal, kept by default
        points = np.random.default_rng(0).uniform(-1, 1, size=(8, 3))
        gaussians = init_from_points(points, np.full((8, 3), 0.5))
        Trainer(gaussians, TrainConfig(), RasterConfig(), 1.0)
        assert float(tiny * 1e-9) == 0.0
    finally:
        torch.set_flush_denormal(False)
