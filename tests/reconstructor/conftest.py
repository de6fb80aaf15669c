"""Fixtures the reconstructor's tests share."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def one_thread():
    """Torch and numba on one thread each for a module: images of 80x50 pixels gain nothing from
    threads, and on a shared, loaded machine the threads of torch and numba wait for each other
    (one thread each ran test_auxiliary.py ~4x faster)."""
    import numba
    import torch

    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(before[0])
    numba.set_num_threads(before[1])


@pytest.fixture(scope="module")
def tiny_session(tmp_path_factory):
    """Six consecutive sets (15 fps, 2.0 s to 2.33 s) of the intraoperative sim, and a tiny
    config (tests/reconstructor/tiny.py): (the session file, the config file)."""
    from tests.reconstructor.tiny import tiny_config_toml, tiny_eval_session

    root = tmp_path_factory.mktemp("case")
    folder = tiny_eval_session(root, sets=6)
    config = root / "tiny.toml"
    config.write_text(tiny_config_toml(3))
    return folder / "session.h5", config
