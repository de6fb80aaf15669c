"""Fixtures of the capture side's tests."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

FAKES = Path(__file__).resolve().parents[1] / "fakes"


@pytest.fixture
def fake_sl(monkeypatch, tmp_path):
    """Put tests/fakes first on sys.path, so ``import pyzed.sl`` finds the replaying fake."""
    monkeypatch.syspath_prepend(str(FAKES))
    for name in ("pyzed.sl", "pyzed"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    import pyzed.sl as sl

    assert Path(sl.__file__).is_relative_to(FAKES)
    monkeypatch.setattr(sl, "REPLAY_DIR", tmp_path / "replay")
    yield sl
    for name in ("pyzed.sl", "pyzed"):
        sys.modules.pop(name, None)
