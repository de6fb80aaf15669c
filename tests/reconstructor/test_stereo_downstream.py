"""bench/bench_stereo_downstream.py: the stereo settings' downstream table in EVALUATION.md.
A reader relies on every difference being paired on the same (timestamp, view) in both runs,
made scene by scene into separate folders, and on depth reprojection's holes and drawn PSNR
being reported beside its score."""

from __future__ import annotations

import json
from pathlib import Path

from bench.bench_stereo_downstream import per_view, read_run, summary


def _record(out: Path, scene: str, config: str, scores: dict[tuple[str, str], float]) -> None:
    """One evaluate --out folder's job record: near-field scores of ``scene``'s views."""
    jobs = out / "jobs"
    jobs.mkdir(parents=True)
    image_scores = []
    for (view, method), db in scores.items():
        reproj = method == "depth-reprojection"
        image_scores.append(
            {"protocol": "near-field", "method": method, "phase": "setup", "scene": scene,
             "view": view, "psnr_db": db, "ssim": 0.5, "lpips": None,
             "holes": 0.25 if reproj else None, "drawn_psnr_db": db + 10 if reproj else None}
        )  # fmt: skip
    record = {"settings": {"config": config}, "image_scores": image_scores}
    (jobs / f"{scene.replace('@', '_')}_left.json").write_text(json.dumps(record))
    (out / "settings.json").write_text("{}")  # not a job record: not read


def test_differences_are_paired_by_timestamp_and_view(tmp_path: Path) -> None:
    base, dense = tmp_path / "base", tmp_path / "dense"
    # the same camera name at two timestamps: they must not be mixed up
    ego, reproj = "egosurg", "depth-reprojection"
    _record(
        base / "a",
        "a@set0",
        "base.toml",
        {("cam1", ego): 30.0, ("cam2", ego): 28.0, ("cam1", reproj): 8.0, ("cam2", reproj): 9.0},
    )
    _record(base / "b", "b@set0", "base.toml", {("cam1", ego): 20.0, ("cam1", reproj): 7.0})
    _record(
        dense / "a",
        "a@set0",
        "dense.toml",
        {("cam1", ego): 31.0, ("cam2", ego): 24.0, ("cam1", reproj): 8.5, ("cam2", reproj): 9.5},
    )
    _record(dense / "b", "b@set0", "dense.toml", {("cam1", ego): 20.5, ("cam1", reproj): 7.0})
    b_scores, b_configs, _ = read_run([base / "a", base / "b"])
    d_scores, d_configs, _ = read_run([dense / "a", dense / "b"])
    assert b_configs == {"base.toml"} and d_configs == {"dense.toml"}
    keys = sorted(set(b_scores) & set(d_scores))
    assert len(keys) == 6
    runs = [("default", b_scores), ("dense", d_scores)]
    text = summary(runs, keys)
    # EgoSurg: scenes (timestamps) a (29.0) and b (20.0) -> 24.50 ± 6.36; dense a 27.5, b 20.5;
    # paired over the three views: +1.0, -4.0, +0.5 -> -0.83 ± 2.75, two of three better
    assert "| EgoSurg | default | 24.50 ± 6.36 |" in text
    dense_row = "| EgoSurg | dense | 24.00 ± 4.95 | 0.500 ± 0.000 | -0.83 ± 2.75 | 2 / 3 |"
    assert dense_row in text
    # depth reprojection's holes (25 %) and PSNR over its drawn pixels (score + 10 here)
    assert "| 25.0 | 18.00 |" in text and "| 25.0 | 18.33 |" in text
    rows = per_view(runs, keys, "near-field").splitlines()
    a_cam2 = next(r for r in rows if r.startswith("| a@set0 | cam2 |"))
    # depth reprojection first (sorted), then EgoSurg: cam2 at a lost 4 dB, b's cam1 is its own
    assert a_cam2 == (
        "| a@set0 | cam2 | 9.00 | +0.50 | 25.0 | 25.0 | 19.00 | +0.50 | 28.00 | -4.00 |"
    )
    b_cam1 = next(r for r in rows if r.startswith("| b@set0 | cam1 |"))
    assert b_cam1.endswith("| 20.00 | +0.50 |")
