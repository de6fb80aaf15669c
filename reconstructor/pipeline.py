"""One timestamp, end to end: stereo depth -> fused points -> Gaussians -> training -> export.

Outputs, in the run's folder:
- ``splats.ply``: the model in the INRIA 3DGS layout (opens in common 3DGS viewers);
- ``points.ply``: the fused, cleaned point cloud the Gaussians started from;
- ``config.toml``: the resolved configuration;
- ``calibration.toml``: the calibration used, so views can be named by sensor later;
- ``summary.json``: the set, its time, missing cameras, counts, timings and the final loss;
- ``log.txt``: the run's log.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

from protocol.rig_calibration import RigCalibration
from reconstructor import ply
from reconstructor.config import ReconstructConfig
from reconstructor.depth_fill import fill_points_in_world
from reconstructor.frames import Timestamp, calibration_at, right_from_left
from reconstructor.fusion import FusedCloud, fuse
from reconstructor.gaussians import Gaussians, init_from_points
from reconstructor.stereo import DepthMap, compute_depth
from reconstructor.stereo_plugins import load_matcher
from reconstructor.train import StepStats, Trainer, scene_extent_m
from reconstructor.views import View, view_from_image

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int, StepStats], None]
# called after warm-up with the trainer and the input views; returns the views for refinement
RefineHook = Callable[[Trainer, Sequence[View]], Sequence[View]]


@dataclass
class Reconstruction:
    """What one timestamp's run made, in memory and on disk."""

    timestamp: Timestamp
    config: ReconstructConfig
    gaussians: Gaussians
    fused: FusedCloud
    depth: dict[str, DepthMap]
    train_views: list[View]
    held_out_views: list[View]
    trainer: Trainer
    out_dir: Path | None
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def model_path(self) -> Path | None:
        return None if self.out_dir is None else self.out_dir / "splats.ply"


def make_views(ts: Timestamp, config: ReconstructConfig) -> tuple[list[View], list[View]]:
    """(training views, held-out views): every sensor, or the left ones for near-field tests."""
    train, held = [], []
    for frame in ts.frames:
        view = view_from_image(
            frame.camera, frame.image_rgb, max_width_px=config.train_max_width_px
        )
        if config.train_views == "left" and frame.side == "right":
            held.append(view)
        else:
            train.append(view)
    return train, held


def stereo_clouds(
    ts: Timestamp, config: ReconstructConfig
) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, DepthMap]]:
    """Each stereo camera's depth as world points with colours."""
    assert config.stereo is not None, "resolve the config first"
    weights = Path(config.stereo_weights) if config.stereo_weights else None
    matcher = load_matcher(config.stereo_matcher, weights, config=config.stereo)
    clouds, depths = [], {}
    for left, right in ts.stereo_pairs():
        depth = compute_depth(
            left.image_rgb,
            right.image_rgb,
            left.camera.intrinsics,
            right.camera.intrinsics,
            right_from_left(left.camera, right.camera),
            config.stereo,
            matcher=matcher,
        )
        depths[f"SN{left.camera_serial}"] = depth
        clouds.append(depth.points_in_world(left.camera.pose))
        filled = fill_points_in_world(
            depth,
            left.camera.pose,
            config.fill,
            min_depth_m=config.stereo.min_depth_m,
            max_depth_m=config.stereo.max_depth_m,
        )
        clouds.append(filled)
        log.info(
            "SN%d: stereo depth valid on %.0f %% of the pixels; %d points filled in blank areas",
            left.camera_serial,
            100 * depth.valid_fraction,
            len(filled[0]),
        )
    return clouds, depths


def reconstruct(
    ts: Timestamp,
    config: ReconstructConfig,
    out_dir: Path | None = None,
    *,
    calibration: RigCalibration | None = None,
    progress: Progress | None = None,
    refine: RefineHook | None = None,
) -> Reconstruction:
    """Reconstruct one timestamp; write the outputs when ``out_dir`` is given."""
    cfg = config.resolved(ts.frames[0].camera.intrinsics.width_px)
    timings: dict[str, float] = {}
    handler = None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(out_dir / "log.txt", mode="w")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        handler.setLevel(logging.INFO)
        logging.getLogger("reconstructor").addHandler(handler)
        logging.getLogger("reconstructor").setLevel(logging.INFO)
        (out_dir / "config.toml").write_text(cfg.to_toml())
        if calibration is not None:  # at the session's size, so sensors render at it by name
            calibration_at(calibration, ts.resolution).write(out_dir / "calibration.toml")
    try:
        log.info(
            "reconstructing %s at set %d (t = %.3f s) from %d sensors%s",
            ts.session,
            ts.set_index,
            ts.t_s,
            len(ts.frames),
            (
                f"; missing cameras {', '.join(f'SN{s}' for s in ts.missing_serials)}"
                if ts.missing_serials
                else ""
            ),
        )
        t0 = time.perf_counter()
        clouds, depths = stereo_clouds(ts, cfg)
        timings["stereo"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        fused = fuse(clouds, cfg.fusion)
        log.info("fused points: %s", fused.stats)
        gaussians = init_from_points(fused.points_m, fused.colours, cfg.init)
        timings["fusion_init"] = time.perf_counter() - t0

        train_views, held_out = make_views(ts, cfg)
        trainer = Trainer(gaussians, cfg.train, cfg.raster, scene_extent_m(train_views))
        t0 = time.perf_counter()
        trainer.run(train_views, cfg.train.warmup_steps, stage="warm-up", progress=progress)
        timings["warmup"] = time.perf_counter() - t0
        refine_views: Sequence[View] = train_views
        if refine is not None and cfg.train.refine_steps > 0:
            t0 = time.perf_counter()
            refine_views = refine(trainer, train_views)
            timings["auxiliary_views"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        trainer.run(refine_views, cfg.train.refine_steps, stage="refinement", progress=progress)
        timings["refinement"] = time.perf_counter() - t0
        result = Reconstruction(
            timestamp=ts,
            config=cfg,
            gaussians=gaussians.detach_clone(),
            fused=fused,
            depth=depths,
            train_views=train_views,
            held_out_views=held_out,
            trainer=trainer,
            out_dir=out_dir,
            timings_s=timings,
        )
        if out_dir is not None:
            write_outputs(result)
        return result
    finally:
        if handler is not None:
            logging.getLogger("reconstructor").removeHandler(handler)
            handler.close()


def write_outputs(result: Reconstruction) -> None:
    out = result.out_dir
    assert out is not None
    ply.write_ply(out / "splats.ply", result.gaussians)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(result.fused.points_m.astype(np.float64))
    pcd.colors = o3d.utility.Vector3dVector(result.fused.colours.astype(np.float64))
    o3d.io.write_point_cloud(str(out / "points.ply"), pcd)  # type: ignore[arg-type]
    ts = result.timestamp
    summary: dict[str, Any] = {
        "session": str(ts.session),
        "set_index": ts.set_index,
        "set_unix_ns": ts.set_unix_ns,
        "t_s": ts.t_s,
        "sensors": [f.camera.name for f in ts.frames],
        "missing_cameras": [f"SN{s}" for s in ts.missing_serials],
        "train_views": [v.name for v in result.train_views],
        "held_out_views": [v.name for v in result.held_out_views],
        "gaussians": result.gaussians.num,
        "fusion": result.fused.stats,
        "steps": result.trainer.step_index,
        "final_loss": result.trainer.log.mean_loss(),
        "timings_s": {k: round(v, 3) for k, v in result.timings_s.items()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    log.info("wrote %s (%d Gaussians)", out / "splats.ply", result.gaussians.num)


def _json_default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    return str(v)
