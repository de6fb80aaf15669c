"""``egosurg case info`` never calls a model "done" that is gone or changed: a deleted model is
MISSING, a cut one DAMAGED (by size, always), a changed one DAMAGED with ``--verify`` (by its
checksum), and a model from before checksums were recorded says it is unchecked.

A real case folder (its index written by ``CaseIndex``, model files on disk, damaged with plain
file writes) and the real ``egosurg`` dispatcher, in this process."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from reconstructor.case.index import CaseIndex, Entry, checksum_file
from tests.helpers import egosurg_in_process


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """Five done timestamps; t3 deleted, t4 one byte changed, t5 cut short, t6 an old entry
    without a checksum; t1 and t2 as written."""
    case = tmp_path / "case"
    (case / "models").mkdir(parents=True)
    entries = []
    for k in range(1, 7):
        model = case / "models" / f"t{k}.ply"
        model.write_bytes(os.urandom(50_000 + k))
        digest, size = checksum_file(model)
        if k == 6:
            digest = ""  # a case written before checksums were recorded
        entries.append(
            Entry(name=f"t{k}", t_s=float(k), set_index=k, model=f"models/t{k}.ply",
                  xxh3_64=digest, bytes=size, status="done", seconds=1.0, gaussians=10)
        )  # fmt: skip
    index = CaseIndex(session="/nowhere/s.h5", session_started_unix_ns=1, config_hash="c",
                      warm_start=False, created_unix_ns=1, timestamps=tuple(entries))  # fmt: skip
    index.write(case)
    (case / "models" / "t3.ply").unlink()
    changed = bytearray((case / "models" / "t4.ply").read_bytes())
    changed[1000] ^= 0x01
    (case / "models" / "t4.ply").write_bytes(bytes(changed))
    os.truncate(case / "models" / "t5.ply", 20_000)
    return case


def _rows(stdout: str) -> dict[str, str]:
    return {line.split()[0]: line for line in stdout.splitlines() if line.startswith("t")}


def test_case_info_shows_missing_and_cut_models_and_exits_1(folder, capsys):
    done = egosurg_in_process(capsys, "case", "info", str(folder))
    assert done.returncode == 1, done.stdout
    rows = _rows(done.stdout)
    assert " MISSING " in rows["t3"] and "models/t3.ply is missing" in rows["t3"]
    assert " DAMAGED " in rows["t5"] and "20000 bytes" in rows["t5"]
    assert " done " in rows["t1"] and " done " in rows["t2"]
    assert " done " in rows["t4"]  # same size: only its checksum can tell (--verify)
    assert "done?" in rows["t6"] and "no checksum was recorded" in rows["t6"]
    assert "1 MISSING, 1 DAMAGED, 1 unchecked" in done.stdout


def test_case_info_verify_finds_a_changed_model_by_its_checksum(folder, capsys):
    done = egosurg_in_process(capsys, "case", "info", str(folder), "--verify")
    assert done.returncode == 1, done.stdout
    rows = _rows(done.stdout)
    assert " DAMAGED " in rows["t4"] and "does not match its checksum" in rows["t4"]
    assert "by checksum: 2 as written, 1 MISSING, 2 DAMAGED, 1 unchecked" in done.stdout


def test_case_info_of_an_intact_case_exits_0(folder, capsys):
    index = CaseIndex.read(folder)
    keep = tuple(e for e in index.timestamps if e.name in ("t1", "t2"))
    CaseIndex(**{**index.__dict__, "timestamps": keep}).write(folder)
    done = egosurg_in_process(capsys, "case", "info", str(folder), "--verify")
    assert done.returncode == 0, done.stdout
    assert "2 as written, 0 MISSING, 0 DAMAGED, 0 unchecked" in done.stdout
