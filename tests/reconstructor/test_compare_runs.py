"""bench/compare_runs.py: the one-change-at-a-time table EVALUATION.md's sections are made with.
A reader relies on its paired differences being over the same views in every run."""

from __future__ import annotations

import json
from pathlib import Path

from bench.compare_runs import common_keys, read_scores, refinement_worth, table


def _record(folder: Path, name: str, scores: dict[tuple[str, str], float]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    image_scores = [
        {"protocol": "egocentric", "method": m, "phase": "setup", "scene": s, "view": s,
         "psnr_db": db, "ssim": 0.5, "lpips": None}
        for (s, m), db in scores.items()
    ]  # fmt: skip
    image_scores.append(
        {"protocol": "near-field", "method": "egosurg", "phase": "setup", "scene": "nf",
         "view": "nf", "psnr_db": 99.0, "ssim": 1.0, "lpips": None}
    )  # fmt: skip
    (folder / f"{name}.json").write_text(json.dumps({"image_scores": image_scores}))


def test_pairs_only_the_views_every_run_scored(tmp_path: Path) -> None:
    base, variant = tmp_path / "base" / "jobs", tmp_path / "var"
    _record(base, "a", {("v1", "egosurg"): 20.0, ("v1", "no-refinement"): 19.0,
                        ("v2", "egosurg"): 22.0, ("v2", "no-refinement"): 22.5,
                        ("v3", "egosurg"): 30.0})  # fmt: skip
    (base.parent / "settings.json").write_text("{}")  # not a job record: not read
    _record(variant / "p0" / "jobs", "a", {("v1", "egosurg"): 21.0, ("v1", "no-refinement"): 19.0})
    _record(variant / "p1" / "jobs", "b", {("v2", "egosurg"): 21.0, ("v2", "no-refinement"): 22.0})
    runs = [read_scores([base.parent], "egocentric"), read_scores([variant], "egocentric")]
    assert ("nf", "egosurg") not in runs[0]  # another protocol's scores stay out
    keys, left_out = common_keys(runs, ["no-refinement", "egosurg"])
    assert {k[0] for k in keys} == {"v1", "v2"} and left_out == 1  # v3: the base's only
    # EgoSurg: v1 +1.0, v2 -1.0 -> 0.00 ± 1.41, one better; worth: base +1.0, -0.5; variant +2, -1
    assert refinement_worth(runs[0], keys) == [1.0, -0.5]
    text = table([("base", runs[0]), ("variant", runs[1])], keys, ["no-refinement", "egosurg"])
    assert "| EgoSurg, variant | 21.00 ± 0.00 | 0.500 ± 0.000 | 0.00 ± 1.41 | 1 / 2 |" in text
    assert "| EgoSurg w/o refinement, variant | 20.50 ± 2.12 |" in text
    assert "| refinement's worth, variant | | | 0.50 ± 2.12 | 1 / 2 |" in text


def test_near_field_views_of_one_timestamp_are_paired_each_with_its_own(tmp_path: Path) -> None:
    """The near-field protocol scores each held-out camera of a timestamp under one scene: a
    comparison over the timestamp's views must keep all four, not the last one read."""

    def record(folder: Path, psnr_db: dict[str, float]) -> None:
        folder.mkdir(parents=True)
        scores = [
            {"protocol": "near-field", "method": "egosurg", "phase": "setup", "scene": "setup@set0",
             "view": view, "psnr_db": db, "ssim": 0.9, "lpips": None}
            for view, db in psnr_db.items()
        ]  # fmt: skip
        (folder / "job.json").write_text(json.dumps({"image_scores": scores}))

    record(tmp_path / "base", {"camA-right": 30.0, "camB-right": 20.0})
    record(tmp_path / "var", {"camA-right": 31.0, "camB-right": 17.0})
    runs = [read_scores([tmp_path / p], "near-field") for p in ("base", "var")]
    keys, left_out = common_keys(runs, ["egosurg"])
    assert len(keys) == 2 and left_out == 0
    text = table([("base", runs[0]), ("var", runs[1])], keys, ["egosurg"])
    # camA +1, camB -3: -1.00 ± 2.83, one view of two better
    assert "| EgoSurg, var | 24.00 ± 9.90 | 0.900 ± 0.000 | -1.00 ± 2.83 | 1 / 2 |" in text
