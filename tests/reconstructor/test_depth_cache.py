"""The depth cache (``reconstructor/depth/cache.py``, ``egosurg evaluate --depth-cache``): a
timestamp's stereo depth and fused cloud made once, kept on disk, and read back on a machine
that has neither OpenCV's contrib modules nor open3d (the lent GPU machines), giving the same
inputs to training as computing them there would."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import logging
import sys

import cv2
import numpy as np
import pytest

from protocol.formats.rig_calibration import RigCalibration
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import load_timestamp
from reconstructor.depth.cache import DepthCache, describe_made_by, stage_key
from reconstructor.errors import DepthCacheError
from reconstructor.pipeline import reconstruct
from tests.helpers import run_egosurg
from tests.reconstructor.tiny import tiny_config_toml, tiny_eval_session


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """One set of the intraoperative sim, its calibration and a tiny config."""
    root = tmp_path_factory.mktemp("depth_cache")
    folder = tiny_eval_session(root, sets=1)
    calibration = RigCalibration.read(folder / "calibration.toml")
    ts = load_timestamp(folder / "session.h5", calibration, "set:0")
    (root / "tiny.toml").write_text(tiny_config_toml(2, fill=True))
    cfg = ReconstructConfig.read(root / "tiny.toml")
    return root, ts, calibration, cfg


def _same_depth(a, b) -> None:
    assert a.keys() == b.keys()
    for name in a:
        x, y = a[name], b[name]
        assert np.array_equal(x.valid, y.valid), name
        assert np.array_equal(x.depth_m, y.depth_m, equal_nan=True), name
        assert np.array_equal(x.rgb, y.rgb), name
        assert x.intrinsics == y.intrinsics and x.baseline_m == y.baseline_m
        assert np.array_equal(x.rect_from_left, y.rect_from_left)
        # what is stored of the disparity: the kept pixels' (fb / depth), to float rounding
        np.testing.assert_allclose(y.disparity_px[y.valid], x.disparity_px[x.valid], rtol=1e-5)


def test_a_stored_depth_stage_trains_on_a_machine_without_opencv_contrib_or_open3d(
    scene, tmp_path, monkeypatch
):
    _, ts, calibration, cfg = scene
    computed = reconstruct(ts, cfg, calibration=calibration)
    made = DepthCache(tmp_path / "dc")
    first = reconstruct(ts, cfg, calibration=calibration, depth_cache=made)
    assert (made.misses, made.hits) == (1, 0)
    assert len(list((tmp_path / "dc").glob("*.npz"))) == 1
    assert not list((tmp_path / "dc").glob(".*tmp")), "no temporary file is left behind"

    # another machine: the SGBM+WLS matcher (contrib) and fusion (open3d) cannot run there
    monkeypatch.delattr(cv2, "ximgproc")
    monkeypatch.setitem(sys.modules, "open3d", None)
    elsewhere = DepthCache(tmp_path / "dc")
    again = reconstruct(ts, cfg, calibration=calibration, depth_cache=elsewhere)
    assert (elsewhere.misses, elsewhere.hits) == (0, 1)
    for result in (first, again):
        _same_depth(computed.depth, result.depth)
        assert np.array_equal(result.fused.points_m, computed.fused.points_m)
        assert np.array_equal(result.fused.colours, computed.fused.colours)
        assert result.fused.stats == computed.fused.stats
    assert again.gaussians.num == computed.gaussians.num
    # what made the depth is the machine that computed it, not the one that reads it
    made_here = {"opencv": cv2.__version__, "open3d": importlib.metadata.version("open3d")}
    assert made.served == elsewhere.served == [made_here]


def test_only_what_the_depth_stage_reads_changes_its_key(scene):
    _, ts, _, cfg = scene
    resolved = cfg.resolved(ts.frames[0].camera.intrinsics.width_px)
    key = stage_key(ts, resolved)
    # the training settings differ between an evaluation's rows: they share one entry
    longer = dataclasses.replace(cfg.train, warmup_steps=500, refine_steps=1500)
    assert stage_key(ts, dataclasses.replace(resolved, train=longer)) == key
    # a different fusion setting, or one changed pixel, is a different entry
    coarser = dataclasses.replace(resolved.fusion, voxel_m=resolved.fusion.voxel_m * 2)
    assert stage_key(ts, dataclasses.replace(resolved, fusion=coarser)) != key
    image = ts.frames[0].image_rgb.copy()
    image[0, 0, 0] ^= 1
    frames = (dataclasses.replace(ts.frames[0], image_rgb=image), *ts.frames[1:])
    assert stage_key(dataclasses.replace(ts, frames=frames), resolved) != key


def test_a_damaged_entry_is_made_again_and_a_file_is_not_a_cache_folder(scene, tmp_path, caplog):
    root, ts, calibration, cfg = scene
    cache = DepthCache(tmp_path / "dc")
    reconstruct(ts, cfg, calibration=calibration, depth_cache=cache)
    (entry,) = (tmp_path / "dc").glob("*.npz")
    entry.write_bytes(entry.read_bytes()[:1000])  # a copy cut short
    fresh = DepthCache(tmp_path / "dc")
    with caplog.at_level(logging.WARNING, logger="reconstructor.depth.cache"):
        reconstruct(ts, cfg, calibration=calibration, depth_cache=fresh)
    assert "unreadable" in caplog.text and (fresh.misses, fresh.hits) == (1, 0)
    assert DepthCache(tmp_path / "dc").get(ts, fresh_cfg(cfg, ts)) is not None  # written again

    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    with pytest.raises(DepthCacheError, match="is a file; give a folder"):
        DepthCache(a_file)
    r = run_egosurg(
        "evaluate", str(root / "es"), "--out", str(tmp_path / "ev"), "--depth-cache", str(a_file)
    )
    assert r.returncode != 0
    assert "is a file; give a folder" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "ev").exists(), "nothing is written before the options are checked"


def fresh_cfg(cfg: ReconstructConfig, ts) -> ReconstructConfig:
    return cfg.resolved(ts.frames[0].camera.intrinsics.width_px)


def test_a_case_rerun_with_other_training_settings_reuses_the_stored_depth(scene, tmp_path):
    root, _, _, _ = scene
    session = root / "es" / "intraoperative" / "session.h5"
    common = ["--every", "1s", "--config", str(root / "tiny.toml")]
    cache = tmp_path / "depth"
    first = run_egosurg(
        "reconstruct", str(session), *common, "--out", str(tmp_path / "a"), "--depth-cache",
        str(cache),
    )  # fmt: skip
    assert first.returncode == 0, first.stderr
    assert len(list(cache.glob("*.npz"))) == 1
    assert "from the depth cache" not in first.stderr
    second = run_egosurg(
        "reconstruct", str(session), *common, "--steps", "3", "--out", str(tmp_path / "b"),
        "--depth-cache", str(cache),
    )  # fmt: skip
    assert second.returncode == 0, second.stderr
    assert second.stderr.count("from the depth cache") == 1
    assert len(list(cache.glob("*.npz"))) == 1


def _rewrite_meta(entry, **changes) -> None:
    """Rewrite a stored entry's meta: ``changes`` set (None: removed)."""
    with np.load(entry) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["meta"].tobytes().decode())
    for k, v in changes.items():
        if v is None:
            meta.pop(k)
        else:
            meta[k] = v
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with open(entry, "wb") as f:
        np.savez_compressed(f, **arrays)


def test_an_entry_from_before_the_libraries_were_kept_reads_as_made_by_unknown(
    scene, tmp_path, caplog
):
    """Depth caches written by earlier versions stay usable; what made them is then unknown,
    and said so, rather than taken for this machine's libraries. An entry whose makers are
    not {library: version} is damaged: made again."""
    _, ts, calibration, cfg = scene
    reconstruct(ts, cfg, calibration=calibration, depth_cache=DepthCache(tmp_path / "dc"))
    (entry,) = (tmp_path / "dc").glob("*.npz")
    with np.load(entry) as z:
        assert json.loads(z["meta"].tobytes().decode())["made_by"]["opencv"] == cv2.__version__
    _rewrite_meta(entry, made_by=None)
    stage = DepthCache(tmp_path / "dc").get(ts, fresh_cfg(cfg, ts))
    assert stage is not None and stage.made_by == {}
    assert describe_made_by(stage.made_by).startswith("unknown libraries")
    assert describe_made_by({"open3d": "0.19.0", "opencv": "4.11.0"}) == (
        "OpenCV 4.11.0, open3d 0.19.0"
    )
    _rewrite_meta(entry, made_by="OpenCV 4")
    with caplog.at_level(logging.WARNING, logger="reconstructor.depth.cache"):
        assert DepthCache(tmp_path / "dc").get(ts, fresh_cfg(cfg, ts)) is None
    assert "unreadable" in caplog.text
