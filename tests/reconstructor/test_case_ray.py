"""A case on a local Ray instance (``ray.init(num_cpus=2)``) makes the same models as the local
process pool: a user can move a case to a cluster without changing its results. The case is
warm-started, the default: each chain (a keyframe and the timestamps warm-started from it)
is one unit of work, on a worker process or as a Ray task."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from reconstructor.case.index import CaseIndex
from reconstructor.case.storage import load_model
from tests.helpers import run_egosurg

ray = pytest.importorskip("ray")


def _models(folder: Path) -> dict[str, dict]:
    rows = json.loads((folder / "case.json").read_text())["timestamps"]
    assert rows and all(r["status"] == "done" for r in rows), rows
    return {r["name"]: r for r in rows}


@pytest.mark.slow  # starting Ray takes 10-30 s on 2 loaded cores
def test_ray_tasks_make_the_same_models_as_the_local_pool(tiny_session, tmp_path):
    from reconstructor.cli import main_reconstruct

    h5, config = tiny_session
    common = ["--config", str(config), "--every", "0.1s", "--to", "2.2", "--workers", "2",
              "--warm-steps", "3", "--keyframe-every", "2"]  # fmt: skip
    pool = tmp_path / "pool"
    done = run_egosurg("reconstruct", str(h5), "--out", str(pool), *common, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]

    on_ray = tmp_path / "ray"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        assert main_reconstruct([str(h5), "--out", str(on_ray), "--ray", "auto", *common]) == 0
    finally:
        ray.shutdown()
    a, b = _models(pool), _models(on_ray)
    assert a.keys() == b.keys() and len(a) == 3
    assert [a[n]["warm_from"] != "" for n in a] == [False, True, False]  # two chains
    ia, ib = CaseIndex.read(pool).by_name(), CaseIndex.read(on_ray).by_name()
    for name in a:
        ga, gb = load_model(pool, ia[name]), load_model(on_ray, ib[name])
        for key, value in ga.parameters_dict().items():
            np.testing.assert_allclose(
                value.numpy(), gb.parameters_dict()[key].numpy(), atol=1e-5, err_msg=name
            )
    # same threads per task, same seed: the files are identical byte for byte
    assert [a[n]["xxh3_64"] for n in a] == [b[n]["xxh3_64"] for n in a]
