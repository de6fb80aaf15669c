"""Compact storage of a warm-started case (reconstructor/case/storage.py): a chain's keyframe
once and each later timestamp as its changes, read back within 0.1 dB of the trained models,
exported as standard PLYs with unit quaternions, damage found by checksum, old cases still read.
Reconstructions are the tiny ones of test_case.py (96 px wide, a few steps)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from protocol.formats.rig_calibration import RigCalibration
from reconstructor.case import storage
from reconstructor.case.index import CaseIndex, Entry, checksum_file
from reconstructor.case.warm import WarmStartConfig, seed_from_previous, warm_config
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.errors import CaseStorageError
from reconstructor.evaluation.metrics import psnr
from reconstructor.pipeline import reconstruct
from reconstructor.replay.models import CaseModels
from reconstructor.splats import ply
from tests.helpers import run_egosurg
from tests.reconstructor.test_ply import random_gaussians
from tests.reconstructor.tiny import tiny_config_toml


def _psnr(g, view, raster) -> float:
    from reconstructor.splats.train import render

    with torch.no_grad():
        out = render(g, view, raster, torch.zeros(3)).image.clamp(0, 1)
    return psnr(out, view.image, view.mask)


def test_a_stored_warm_chain_renders_within_a_tenth_of_a_db_of_the_trained_models(
    tiny_session,
    tmp_path,
):
    h5, _ = tiny_session
    calibration = RigCalibration.read(h5.parent / "calibration.toml")
    cold = ReconstructConfig.from_toml(tiny_config_toml(4))
    wcfg = WarmStartConfig(steps=3, keyframe_every=3)
    warm = warm_config(cold, wcfg)
    parent, ref = None, None
    for k in range(3):
        ts = load_timestamp(h5, calibration, f"set:{k}")
        lineage: dict = {}
        if parent is None:
            result = reconstruct(ts, cold)
        else:
            previous = parent.gaussians()  # as a resumed run would: from the stored form

            def init(ts_, fused, depths, previous=previous, lineage=lineage):
                seed = seed_from_previous(previous, ts_, fused, depths, wcfg, warm.init)
                lineage["alive"] = seed.alive
                assert seed.alive.sum() == seed.counts["kept"]
                return seed.gaussians

            result = reconstruct(ts, warm, init=init)
        path = tmp_path / f"t{k}.npz"
        storage.write_model(
            path, result.gaussians, parent=parent, parent_ref=ref, alive=lineage.get("alive")
        )
        digest, size = checksum_file(path)
        ref = {"model": path.name, "xxh3_64": digest, "bytes": size}
        parent = storage.load_stored(tmp_path, path.name, digest, size)
        assert parent.num == result.gaussians.num
        back = parent.gaussians()
        for view in result.train_views[:2]:
            in_memory = _psnr(result.gaussians, view, result.config.raster)
            stored = _psnr(back, view, result.config.raster)
            assert abs(stored - in_memory) < 0.1, (k, view.name, in_memory, stored)
        if k:  # a change set, not a second copy of the model
            full = ply.write_ply(tmp_path / f"t{k}.ply", result.gaussians).stat().st_size
            assert size < full / 3


@pytest.mark.slow  # two runs of the real command, as test_case.py's case runs
def test_a_warm_case_exports_unit_quaternion_plys_and_a_damaged_change_file_is_named(
    tiny_session,
    tmp_path,
):
    h5, config = tiny_session
    out = tmp_path / "case"
    argv = [
        "reconstruct",
        str(h5),
        "--config",
        str(config),
        "--out",
        str(out),
        "--every",
        "0.1s",
        "--to",
        "2.2",
        "--warm-start",
        "--warm-steps",
        "2",
        "--keyframe-every",
        "5",
    ]
    done = run_egosurg(*argv, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((out / "case.json").read_text())["timestamps"]
    assert len(rows) == 3 and all(r["model"].endswith(".npz") for r in rows)
    last = rows[-1]
    exp = run_egosurg(
        "case", "export", str(out), "--out", str(tmp_path / "ply"), "--at", last["name"]
    )
    assert exp.returncode == 0, exp.stderr
    g = ply.read_ply(tmp_path / "ply" / f"{last['name']}.ply")
    assert g.num == last["gaussians"]
    assert np.allclose(np.linalg.norm(g.quats_wxyz.numpy(), axis=1), 1.0, atol=1e-6)

    # the middle timestamp's change file cut short: whatever needs it says so in one line
    middle = out / rows[1]["model"]
    middle.write_bytes(middle.read_bytes()[:-100])
    bad = run_egosurg(
        "case", "export", str(out), "--out", str(tmp_path / "x"), "--at", last["name"]
    )
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    line = bad.stderr.strip().splitlines()[-1]
    assert str(middle) in line and "fails its checksum" in line and "rerun" in line
    # a rerun redoes it and the timestamp stored as changes to it, and keeps the keyframe
    keyframe = (out / rows[0]["model"]).stat().st_mtime_ns
    again = run_egosurg(*argv, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    after = json.loads((out / "case.json").read_text())["timestamps"]
    assert (out / after[0]["model"]).stat().st_mtime_ns == keyframe
    assert after[1]["xxh3_64"] == checksum_file(middle)[0]
    index = CaseIndex.read(out)
    assert CaseModels(out).load(index.timestamps[2]).num == after[2]["gaussians"]


def test_an_old_case_with_a_full_ply_per_timestamp_still_loads(tmp_path):
    g = random_gaussians(50, 1, seed=4)
    model = ply.write_ply(tmp_path / "models" / "t00002.000.ply", g)
    digest, size = checksum_file(model)
    entry = Entry(
        name="t00002.000",
        t_s=2.0,
        set_index=0,
        model="models/t00002.000.ply",
        xxh3_64=digest,
        bytes=size,
        status="done",
        gaussians=50,
    )
    CaseIndex(
        session="s.h5",
        session_started_unix_ns=1,
        config_hash="x",
        warm_start=False,
        created_unix_ns=1,
        timestamps=(entry,),
    ).write(tmp_path)
    for back in (storage.load_model(tmp_path, entry), CaseModels(tmp_path).load(entry)):
        for name, tensor in g.parameters_dict().items():
            assert torch.equal(back.parameters_dict()[name], tensor), name


def test_every_stored_value_is_within_one_grid_step_along_a_chain(tmp_path: Path):
    """Closed loop: a value held from the parent is compared with what a reader decodes, so the
    error does not grow over a chain of small changes."""
    steps = storage.QuantSteps()
    g = random_gaussians(400, 0, seed=1)
    parent, ref = None, None
    gen = torch.Generator().manual_seed(2)
    for k in range(6):
        alive = None
        if parent is not None:  # drop a tenth, nudge the rest a little, add a few
            alive = torch.rand(g.num, generator=gen).numpy() > 0.1
            kept = {n: t[torch.from_numpy(alive)] for n, t in g.parameters_dict().items()}
            kept = {n: t + 3e-4 * torch.randn(t.shape, generator=gen) for n, t in kept.items()}
            fresh = random_gaussians(20, 0, seed=10 + k).parameters_dict()
            g = type(g)(**{n: torch.cat([kept[n], fresh[n]]) for n in kept})
        path = tmp_path / f"m{k}.npz"
        storage.write_model(path, g, parent=parent, parent_ref=ref, alive=alive)
        digest, size = checksum_file(path)
        ref = {"model": path.name, "xxh3_64": digest, "bytes": size}
        parent = storage.load_stored(tmp_path, path.name, digest, size)
        back = parent.gaussians()
        unit = ply.unit_quaternions(g)
        assert (back.means_m - g.means_m).abs().max() <= steps.position_m * 1.001
        assert (back.quats_wxyz - unit.quats_wxyz).abs().max() <= steps.quat * 1.001
        assert (back.sh_dc - g.sh_dc).abs().max() <= steps.sh_dc * 1.001
        assert (back.log_scales - g.log_scales).abs().max() <= steps.log_scale * 1.001


def test_a_timestamp_keeps_the_points_its_stereo_saw_within_half_a_grid_step(tmp_path: Path):
    """The sterile tool judges what the cameras saw (the fused points), not the trained model:
    they are stored in the model's file, under its checksum, and read back to within half a
    grid step; a model stored without them (older cases, PLYs) says so with None."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    points = rng.uniform([-3.0, -2.5, 0.0], [3.0, 2.5, 2.8], size=(5000, 3))
    points[100:110] = points[99]  # stereo repeats points: all are kept
    g = random_gaussians(300, 1, seed=6)
    with_points = tmp_path / "models" / "a.npz"
    without = tmp_path / "models" / "b.npz"
    storage.write_model(with_points, g, points_m=points)
    storage.write_model(without, g)

    def entry(path: Path) -> Entry:
        digest, size = checksum_file(path)
        return Entry(name=path.stem, t_s=0.0, set_index=0, model=f"models/{path.name}",
                     xxh3_64=digest, bytes=size, status="done", gaussians=g.num)  # fmt: skip

    back = storage.load_points(tmp_path, entry(with_points))
    assert back is not None and back.shape == points.shape
    dist, _ = cKDTree(back).query(points)
    assert dist.max() <= storage.POINTS_STEP_M * np.sqrt(3) / 2 + 1e-12
    assert len(np.unique(np.rint(back / storage.POINTS_STEP_M), axis=0)) == 5000 - 10
    # the points change nothing about the model
    a = storage.load_model(tmp_path, entry(with_points))
    b = storage.load_model(tmp_path, entry(without))
    for name, tensor in a.parameters_dict().items():
        assert torch.equal(b.parameters_dict()[name], tensor), name
    assert storage.load_points(tmp_path, entry(without)) is None
    # a file damaged after its checksum was taken is named, not read
    good = entry(with_points)
    blob = bytearray(with_points.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    with_points.write_bytes(bytes(blob))
    with pytest.raises(CaseStorageError, match=r"a\.npz.*fails its checksum"):
        storage.load_points(tmp_path, good)


def _rewrite(path: Path, arrays: dict[str, bytes], compress: int = 0) -> None:
    """A model file with these raw .npy members (a crafted or damaged file, as a hostile
    case folder would hold it)."""
    import zipfile

    with zipfile.ZipFile(path, "w", compress or zipfile.ZIP_STORED) as zf:
        for key, raw in arrays.items():
            zf.writestr(f"{key}.npy", raw)


def _npy(array: np.ndarray, claimed_len: int | None = None) -> bytes:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array(buf, array, allow_pickle=False)
    raw = buf.getvalue()
    if claimed_len is not None:  # the header claims more bytes than follow
        raw = raw.replace(f"({len(array)},)".encode(), f"({claimed_len},)".encode().ljust(
            len(f"({len(array)},)")), 1)  # fmt: skip
    return raw


@pytest.mark.parametrize(
    "craft",
    ["huge_n", "inflate_bomb", "npy_claims_more", "deflated_member", "meta_list", "no_parent"],
)
def test_a_crafted_model_file_is_refused_in_one_line_without_inflating_it(tmp_path, craft):
    """A case folder is input like any other: a model file whose checksum matches (whoever
    altered it rewrote the index too) but whose contents claim more than they hold cannot make
    the reader allocate or inflate beyond the file's own bounds; it gets CaseStorageError
    naming the file, never a MemoryError, a hang or a traceback."""
    import json
    import zlib

    g = random_gaussians(50, 0, seed=3)
    path = tmp_path / "models" / "m.npz"
    storage.write_model(path, g)
    import zipfile

    with zipfile.ZipFile(path) as zf:
        members = {n[:-4]: np.lib.format.read_array(zf.open(n)) for n in zf.namelist()}
    meta = json.loads(members["meta"].tobytes())
    raw = {k: _npy(v) for k, v in members.items()}
    compress = 0
    if craft == "huge_n":  # 10^12 rows claimed by a few hundred bytes
        meta["n"] = 10**12
    elif craft == "inflate_bomb":  # 64 MB of zeros in ~64 kB, for a table of 50 rows
        bomb = zlib.compress(bytes(64 << 20), 9)
        raw["new"] = _npy(np.frombuffer(bomb, np.uint8))
    elif craft == "npy_claims_more":
        raw["new"] = _npy(members["new"], claimed_len=10**11)
    elif craft == "deflated_member":
        compress = zipfile.ZIP_DEFLATED
    elif craft == "meta_list":
        meta = [1, 2, 3]
    elif craft == "no_parent":
        del meta["parent"]
    raw["meta"] = _npy(np.frombuffer(json.dumps(meta).encode(), np.uint8))
    _rewrite(path, raw, compress)
    digest, size = checksum_file(path)
    import tracemalloc

    tracemalloc.start()
    try:
        with pytest.raises(CaseStorageError, match=r"m\.npz") as err:
            storage.load_stored(tmp_path, "models/m.npz", digest, size)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(str(err.value).splitlines()) == 1
    assert peak < 8 << 20, peak  # the bomb would be 64 MB inflated
