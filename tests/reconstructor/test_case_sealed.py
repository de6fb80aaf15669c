"""A sealed session's case, as its readers rely on it: the real ``egosurg reconstruct --every``
(warm start, a depth cache) on a session sealed for a site key leaves no plaintext model or
depth in the case folder or the cache; ``case info --verify`` checks it and finds a changed
byte without a key; ``case export`` and ``replay`` open it with the identity and refuse in one
line, naming the recipients, without it; a model copied to another timestamp does not open,
and says which; a rerun resumes from the sealed models."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration
from protocol.formats.trajectory import Keyframe, Trajectory, write_trajectories
from protocol.sealing import IdentityRequiredError, generate_identity, load_identity
from protocol.sealing.keyfiles import write_identity
from reconstructor.case import storage
from reconstructor.case.index import CaseIndex, checksum_file
from reconstructor.case.sealing import case_seal
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.depth.cache import DepthCache
from reconstructor.errors import CaseStorageError
from reconstructor.replay.models import CaseModels
from reconstructor.splats import ply
from tests.helpers import copy_sets, egosurg_in_process, run_egosurg

# what a plaintext model, point cloud or depth entry starts with, anywhere in a file
PLAINTEXT_MARKS = (b"ply\n", b"PK\x03\x04", b"\x93NUMPY")

pytestmark = pytest.mark.slow  # one real reconstruct of two timestamps (about 20 s) and a rerun


egosurg = egosurg_in_process


@pytest.fixture(scope="module")
def sealed_case(tiny_session, tmp_path_factory):
    """The tiny session's sets copied into a session sealed for ``hospital-a``, reconstructed
    (2.0 and 2.067 s: a keyframe and a warm timestamp stored as its changes) with a depth
    cache; the identity file, the session, the case, the cache and the config."""
    h5, config = tiny_session
    root = tmp_path_factory.mktemp("sealed_case")
    site = generate_identity("hospital-a")
    _recipient, identity = write_identity(site, root / "keys")
    session = root / "session" / "session.h5"
    session.parent.mkdir()
    shutil.copy(h5.parent / "calibration.toml", session.parent / "calibration.toml")
    copy_sets(h5, session, np.arange(6), recipients=[site.recipient])
    case, cache = root / "case", root / "depth"
    done = run_egosurg(
        "reconstruct", str(session), "--config", str(config), "--every", "0.0667s",
        "--to", "2.07", "--out", str(case), "--depth-cache", str(cache),
        "--identity", str(identity), timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return {"identity": identity, "session": session, "case": case, "cache": cache,
            "config": config, "plain": h5}  # fmt: skip


@pytest.fixture(autouse=True)
def _no_identity_in_the_environment(monkeypatch):
    monkeypatch.delenv("EGOSURG_IDENTITY", raising=False)


def test_the_case_and_its_depth_cache_hold_no_plaintext_model_or_depth(sealed_case):
    case, cache = sealed_case["case"], sealed_case["cache"]
    index = json.loads((case / "case.json").read_text())
    assert [r["status"] for r in index["timestamps"]] == ["done", "done"]
    assert index["timestamps"][1]["warm_from"] == index["timestamps"][0]["name"]
    assert [r["name"] for r in index["sealing"]["recipients"]] == ["hospital-a"]
    models = sorted(p.name for p in (case / "models").iterdir())
    assert models == [f"{r['name']}.npz.sealed" for r in index["timestamps"]]
    entries = sorted(p.name for p in cache.iterdir())
    assert len(entries) == 2 and all(n.endswith(".npz.sealed") for n in entries), entries
    files = [p for p in [*case.rglob("*"), *cache.rglob("*")] if p.is_file()]
    for path in files:
        data = path.read_bytes()
        found = [m for m in PLAINTEXT_MARKS if m in data]
        assert not found, f"{path} holds {found}"
    assert not list(case.rglob("*.ply")) and not list(case.rglob("*.jpg"))


def test_case_info_verify_checks_the_sealed_models_without_a_key(sealed_case, capsys, tmp_path):
    copy = tmp_path / "case"
    shutil.copytree(sealed_case["case"], copy)
    ok = egosurg(capsys, "case", "info", str(copy), "--verify")
    assert ok.returncode == 0, ok.stderr
    victim = next((copy / "models").iterdir())
    blob = bytearray(victim.read_bytes())
    blob[len(blob) // 2] ^= 0x01
    victim.write_bytes(bytes(blob))
    from protocol.cli import main

    capsys.readouterr()
    assert main(["case", "info", str(copy)]) == 0  # same size: only --verify reads it
    text = capsys.readouterr().out
    assert "models sealed for hospital-a (key id" in text
    assert main(["case", "info", str(copy), "--verify"]) == 1
    text = capsys.readouterr().out
    assert "1 DAMAGED" in text and f"model models/{victim.name} does not match" in text


def test_case_export_opens_with_the_identity_and_refuses_in_one_line_without(
    sealed_case, capsys, tmp_path
):
    case = sealed_case["case"]
    refused = egosurg(capsys, "case", "export", str(case), "--out", str(tmp_path / "no"))
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    line = refused.stderr.strip()
    assert "\n" not in line and "hospital-a (key id" in line and "--identity FILE" in line
    assert not (tmp_path / "no").exists()

    out = tmp_path / "ply"
    done = egosurg(capsys, "case", "export", str(case), "--out", str(out),
                   "--identity", str(sealed_case["identity"]))  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert f"wrote plaintext 2 model(s) as .ply to {out}" in done.stderr
    index = CaseIndex.read(case)
    seal = case_seal(case, index, load_identity(sealed_case["identity"]))
    for e in index.timestamps:
        exported = ply.read_ply(out / f"{e.name}.ply")
        stored = storage.load_model(case, e, seal)
        assert exported.num == stored.num > 100
        assert np.allclose(exported.means_m.numpy(), stored.means_m.numpy(), atol=1e-6)


def test_replay_opens_the_sealed_models_with_the_identity_and_refuses_without(
    sealed_case, capsys, tmp_path
):
    eye = Pose.look_at(np.array([2.5, -2.0, 1.7]), np.array([0.0, 0.0, 1.0]))
    keys = (Keyframe.from_pose(2.0, eye, 80), Keyframe.from_pose(2.06, eye, 80))
    walk = write_trajectories(tmp_path / "walk.toml", [Trajectory(name="walk", keyframes=keys)])
    args = ["replay", str(sealed_case["case"]), "--trajectory", str(walk), "--size", "64x40",
            "--fps", "20"]  # fmt: skip
    refused = egosurg(capsys, *args, "--out", str(tmp_path / "no.mp4"))
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert "hospital-a (key id" in refused.stderr and "--identity FILE" in refused.stderr
    assert not (tmp_path / "no.mp4").exists()
    out = tmp_path / "walk.mp4"
    done = egosurg(capsys, *args, "--out", str(out), "--identity", str(sealed_case["identity"]))
    assert done.returncode == 0, done.stderr[-2000:]
    assert out.stat().st_size > 0 and "wrote plaintext video" in done.stderr
    with pytest.raises(IdentityRequiredError, match="hospital-a"):
        CaseModels(sealed_case["case"])


def test_a_model_copied_to_another_timestamp_does_not_open_and_is_named(sealed_case, tmp_path):
    copy = tmp_path / "case"
    shutil.copytree(sealed_case["case"], copy)
    index = CaseIndex.read(copy)
    first, second = index.timestamps
    target = copy / second.model
    shutil.copyfile(copy / first.model, target)
    digest, size = checksum_file(target)  # the index made to agree: only the seal can tell
    moved = dataclasses.replace(second, xxh3_64=digest, bytes=size)
    index.with_entry(moved).write(copy)
    seal = case_seal(copy, CaseIndex.read(copy), load_identity(sealed_case["identity"]))
    with pytest.raises(CaseStorageError) as e:
        storage.load_model(copy, moved, seal)
    assert str(target) in str(e.value) and f"does not open as model {second.name}" in str(e.value)


def test_the_sealed_depth_cache_serves_the_sealed_session_and_never_the_plaintext_one(sealed_case):
    calibration = RigCalibration.read(sealed_case["session"].parent / "calibration.toml")
    identity = load_identity(sealed_case["identity"])
    cfg = ReconstructConfig.read(sealed_case["config"])
    sealed = load_timestamp(sealed_case["session"], calibration, "set:0", identity=identity)
    plain = load_timestamp(sealed_case["plain"], calibration, "set:0")
    cfg = cfg.resolved(sealed.frames[0].camera.intrinsics.width_px)
    cache = DepthCache(sealed_case["cache"], memory=0)
    stage = cache.get(sealed, cfg)
    assert stage is not None and len(stage.fused.points_m) > 1000
    assert cache.get(plain, cfg) is None  # the same images, but the entry is sealed


def test_a_rerun_resumes_from_the_sealed_models(sealed_case):
    case = sealed_case["case"]
    before = {p.name: p.stat().st_mtime_ns for p in (case / "models").iterdir()}
    again = run_egosurg(
        "reconstruct", str(sealed_case["session"]), "--config", str(sealed_case["config"]),
        "--every", "0.0667s", "--to", "2.07", "--out", str(case),
        "--identity", str(sealed_case["identity"]), timeout=600,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr[-3000:]
    assert "redone" not in again.stderr
    assert {p.name: p.stat().st_mtime_ns for p in (case / "models").iterdir()} == before


def test_a_sealed_sessions_case_with_plaintext_models_is_resumed_sealed(sealed_case, tmp_path):
    """A case of a sealed session made before its models were sealed: the rerun removes the
    plaintext models and redoes them sealed (and the index names the recipients)."""
    copy = tmp_path / "case"
    shutil.copytree(sealed_case["case"], copy)
    index = CaseIndex.read(copy)
    seal = case_seal(copy, index, load_identity(sealed_case["identity"]))
    first = index.timestamps[0]
    sealed_file = copy / first.model
    plain = copy / "models" / f"{first.name}.npz"
    plain.write_bytes(seal.open("model", first.name, sealed_file.read_bytes(), "m"))
    sealed_file.unlink()
    digest, size = checksum_file(plain)
    older = dataclasses.replace(first, model=f"models/{plain.name}", xxh3_64=digest, bytes=size)
    dataclasses.replace(index.with_entry(older), sealing=None).write(copy)
    assert "sealing" not in json.loads((copy / "case.json").read_text())
    again = run_egosurg(
        "reconstruct", str(sealed_case["session"]), "--config", str(sealed_case["config"]),
        "--every", "0.0667s", "--to", "2.07", "--out", str(copy),
        "--identity", str(sealed_case["identity"]), timeout=600,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"{first.name}: its model is missing or damaged; it is redone" in again.stderr
    assert not plain.exists()
    index = json.loads((copy / "case.json").read_text())
    assert index["sealing"]["recipients"][0]["name"] == "hospital-a"
    assert all(r["model"].endswith(".npz.sealed") for r in index["timestamps"])
    for path in (copy / "models").iterdir():
        assert b"PK\x03\x04" not in path.read_bytes(), path


def test_the_viewer_and_the_sterile_tools_points_open_with_the_identity_only(sealed_case, capsys):
    refused = egosurg(capsys, "view", str(sealed_case["case"]), "--port", "0")
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert "hospital-a (key id" in refused.stderr and "--identity FILE" in refused.stderr
    models = CaseModels(sealed_case["case"], load_identity(sealed_case["identity"]))
    for e in models.entries:  # what the sterile-field tool reads: the stereo's points
        points = models.load_points(e)
        assert points is not None and len(points) > 1000 and np.isfinite(points).all()


def test_people_read_a_sealed_cases_own_points_with_the_identity_and_refuse_without(sealed_case):
    """A sealed case whose session is gone: ``egosurg people`` finds people in the points the
    case keeps, which are sealed: opened with a recipient's identity, refused (naming the
    recipients) without one, before any timestamp is read; the cells a second camera confirmed
    (their stored camera masks) are what it reads."""
    from reconstructor.people.sources import SEEN_TWICE_CELL_M, open_source, seen_twice_cells

    case = sealed_case["case"]
    with pytest.raises(IdentityRequiredError, match="hospital-a"):
        open_source(case, use_session=False)
    identity = load_identity(sealed_case["identity"])
    source = open_source(case, identity=identity, use_session=False)
    index = CaseIndex.read(case)
    seal = case_seal(case, index, identity)
    done = [e for e in index.timestamps if e.status == "done"]
    assert len(source.times_s) == len(done) == 2
    for k, entry in enumerate(done):
        points = source.points(k)
        assert points.shape[1] == 3 and len(points) > 100
        seen = storage.load_observation(case, entry, seal)
        assert seen is not None and seen.seen_by is not None and len(seen.cameras) >= 2
        kept = seen_twice_cells(seen.points_m, seen.seen_by, len(seen.cameras),
                                source.room_xy_m, SEEN_TWICE_CELL_M)  # fmt: skip
        assert np.array_equal(points, kept) and len(points) < len(seen.points_m)
