"""A reconstruction small enough to run whole in a test: the first sets of the intraoperative
sim at 64 x 40 pixels, and a config that trains at 96 pixels wide from quarter-scale stereo for
a few steps, without the auxiliary views."""

from __future__ import annotations

from pathlib import Path


def tiny_config_toml(warmup_steps: int, *, fill: bool = False) -> str:
    """The config's TOML; ``fill`` keeps the depth fill of blank walls (off: the fastest)."""
    fill_table = "" if fill else "[fill]\nenabled = false\n"
    return (
        "train_max_width_px = 96\n"
        "[stereo]\nmatch_scale = 0.25\n"
        f"{fill_table}"
        "[fusion]\nmax_points = 20000\n"
        f"[train]\nwarmup_steps = {warmup_steps}\nrefine_steps = 0\n"
        "[auxiliary]\nenabled = false\n"
    )


def tiny_eval_session(root: Path, sets: int) -> Path:
    """Writes an eval set of the intraoperative sim's first ``sets`` sets (15 fps from 2.0 s)
    under ``root / "es"``; the folder holding its session.h5 and calibration.toml."""
    from sim.eval_set import EvalSetSpec, write_eval_set

    spec = EvalSetSpec(
        phases=("intraoperative",), sets=sets, eval_sets=(0,), instants=1, view_size_px=(64, 40)
    )
    write_eval_set(root / "es", spec)
    return root / "es" / "intraoperative"
