"""One timestamp, end to end: stereo depth -> fused points -> Gaussians -> training -> export.

Training is the paper's two stages: warm-up on the input views, then refinement on the input
views plus auxiliary views (``reconstructor/refine/auxiliary.py``) made once after warm-up by the
refiner ``config.auxiliary.refiner``. The refiner is loaded before stereo runs, so a missing
plug-in or weights file fails in a second, not after minutes. A caller's ``refine`` hook, when
given, replaces the auxiliary views.

``init_method = "random"`` (the image-only 3DGS baseline) seeds the Gaussians uniformly in
``room_bounds_m``, or when that is empty in the box the cameras look into (their centres and
their frustums out to where their optical axes meet, above the floor when the calibration's
world frame is the floor). Stereo still runs, unused by training: ``points.ply`` and the
depth-reprojection baseline of ``--evaluate`` need the fused cloud, and the stereo share of a
run is small next to training.

Outputs, in the run's folder:
- ``splats.ply``: the model in the INRIA 3DGS layout (opens in common 3DGS viewers);
- ``points.ply``: the fused, cleaned point cloud the Gaussians started from;
- ``config.toml``: the resolved configuration;
- ``calibration.toml``: the calibration used, so views can be named by sensor later;
- ``summary.json``: the set, its time, missing cameras, counts, timings and the final loss, the
  init method, and the auxiliary views (refiner, count, seconds);
- ``auxiliary_views.jpg``: reference | render | refined for a few auxiliary views (when
  ``auxiliary.save_pictures``);
- ``log.txt``: the run's log.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import Timestamp, calibration_at, right_from_left
from reconstructor.data.views import View, view_from_image
from reconstructor.depth.cache import DepthCache, DepthStage
from reconstructor.depth.fill import fill_points_in_world
from reconstructor.depth.fusion import FusedCloud, fuse
from reconstructor.depth.matchers import load_matcher
from reconstructor.depth.reproject import depth_targets
from reconstructor.depth.stereo import DepthMap, compute_depth
from reconstructor.refine.auxiliary import AuxiliaryConfig, Bounds, make_auxiliary_views
from reconstructor.refine.base import Refiner
from reconstructor.refine.eye_views import make_eye_views
from reconstructor.refine.refiners import load_refiner
from reconstructor.splats import ply
from reconstructor.splats.gaussians import (
    Gaussians,
    init_from_points,
    init_random,
    random_init_box,
)
from reconstructor.splats.train import StepStats, Trainer, ViewGroup, scene_extent_m

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int, StepStats], None]
# called after warm-up with the trainer and the input views; returns the views for refinement
RefineHook = Callable[[Trainer, Sequence[View]], Sequence[View]]
# called after fusion with the timestamp, its fused cloud and depth maps; returns the Gaussians
# training starts from (a case's warm start: the previous timestamp's model, updated)
InitHook = Callable[[Timestamp, FusedCloud, "dict[str, DepthMap]"], Gaussians]


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
    auxiliary: dict[str, Any] = field(default_factory=dict)  # refiner, views, seconds

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
            room_box_m=config.room_box_m,
        )
        clouds.append(filled)
        log.info(
            "SN%d: stereo depth valid on %.0f %% of the pixels; %d points filled in blank areas",
            left.camera_serial,
            100 * depth.valid_fraction,
            len(filled[0]),
        )
    return clouds, depths


def build_refiner(config: AuxiliaryConfig) -> Refiner:
    """The refiner ``config`` names (its weights path when given, the guided settings)."""
    weights = Path(config.refiner_weights) if config.refiner_weights else None
    options = config.guided if config.refiner == "guided" else None
    return load_refiner(config.refiner, weights, config=options)


def world_bounds(config: ReconstructConfig, calibration: RigCalibration | None) -> Bounds | None:
    """``room_bounds_m``; else the floor alone (z >= 0) when the calibration's world frame is the
    floor's; else None."""
    box = config.room_box_m
    if box is not None:
        return box
    if calibration is not None and calibration.world_frame == "floor":
        return np.array([-np.inf, -np.inf, 0.0]), np.full(3, np.inf)
    return None


def reconstruct(
    ts: Timestamp,
    config: ReconstructConfig,
    out_dir: Path | None = None,
    *,
    calibration: RigCalibration | None = None,
    progress: Progress | None = None,
    refine: RefineHook | None = None,
    init: InitHook | None = None,
    depth_cache: DepthCache | None = None,
    write_models: bool = True,
) -> Reconstruction:
    """Reconstruct one timestamp; write the outputs when ``out_dir`` is given (without
    ``splats.ply`` and ``points.ply`` unless ``write_models``: a sealed case seals its own).

    The stages, in order: depth (stereo and hole filling), init (fusion and the Gaussians),
    warm-up, auxiliary views (the refiner's, or the caller's ``refine`` hook), refinement, and
    the outputs. ``timings_s`` of the result has one entry per stage. A caller's ``init`` hook
    replaces the initial Gaussians (the fused cloud is still made and passed to it). With a
    ``depth_cache``, the depth stage (stereo and fusion) is read from it when it holds this
    timestamp under these settings, and kept in it when not.
    """
    cfg = config.resolved(ts.frames[0].camera.intrinsics.width_px)
    timings: dict[str, float] = {}
    refiner = None
    if refine is None and cfg.auxiliary.enabled and cfg.train.refine_steps > 0:
        refiner = build_refiner(cfg.auxiliary)  # before stereo: a bad name fails at once
    with _run_folder(out_dir, cfg, ts, calibration):
        _log_start(ts)
        stage = depth_cache.get(ts, cfg) if depth_cache is not None else None
        with _timed(timings, "stereo"):
            clouds, depths = stereo_clouds(ts, cfg) if stage is None else (None, stage.depths)
        train_views, held_out = make_views(ts, cfg)
        bounds = world_bounds(cfg, calibration)
        with _timed(timings, "fusion_init"):
            if stage is None:
                assert clouds is not None
                fused = fuse(clouds, cfg.fusion)
                log.info("fused points: %s", fused.stats)
                if depth_cache is not None:
                    depth_cache.put(ts, cfg, DepthStage(depths, fused, clouds))
            else:
                fused = stage.fused
                log.info("depth and fused points (%d) from the depth cache", len(fused.points_m))
            if init is None:
                gaussians = _init_gaussians(fused, train_views, bounds, cfg)
            else:  # the hook seeds its own Gaussians: a cold init would be thrown away
                gaussians = init(ts, fused, depths)
        trainer = Trainer(gaussians, cfg.train, cfg.raster, scene_extent_m(train_views))
        if cfg.train.depth_weight > 0:
            with _timed(timings, "depth_targets"):
                trainer.set_depth_targets(depth_targets(train_views, _depth_sources(ts, depths)))
        with _timed(timings, "warmup"):
            trainer.run(train_views, cfg.train.warmup_steps, stage="warm-up", progress=progress)
        refinement = _auxiliary_stage(
            trainer, train_views, cfg, refiner, refine, bounds, out_dir, timings
        )
        with _timed(timings, "refinement"):
            _refinement_stage(trainer, train_views, refinement, cfg, progress)
        result = Reconstruction(
            timestamp=ts,
            config=cfg,
            gaussians=gaussians.detach_clone().to(device="cpu"),  # trained on cuda or not
            fused=fused,
            depth=depths,
            train_views=train_views,
            held_out_views=held_out,
            trainer=trainer,
            out_dir=out_dir,
            timings_s=timings,
            auxiliary=refinement.summary,
        )
        del refinement  # its auxiliary views: nothing needs them after the stage
        if out_dir is not None:
            write_outputs(result, models=write_models)
        return result


def _depth_sources(ts: Timestamp, depths: dict[str, DepthMap]) -> dict[str, tuple[DepthMap, Pose]]:
    """Each sensor's own stereo pair's depth map and that pair's left pose, by camera name."""
    out: dict[str, tuple[DepthMap, Pose]] = {}
    for left, right in ts.stereo_pairs():
        depth = depths.get(f"SN{left.camera_serial}")
        if depth is not None:
            out[left.camera.name] = out[right.camera.name] = (depth, left.camera.pose)
    return out


@contextlib.contextmanager
def _timed(timings: dict[str, float], stage: str) -> Iterator[None]:
    """Adds the seconds the block took to ``timings[stage]``."""
    t0 = time.perf_counter()
    yield
    timings[stage] = time.perf_counter() - t0


@contextlib.contextmanager
def _run_folder(
    out_dir: Path | None,
    cfg: ReconstructConfig,
    ts: Timestamp,
    calibration: RigCalibration | None,
) -> Iterator[None]:
    """The run's folder with its resolved config, calibration and ``log.txt`` (the
    reconstructor's log while the block runs); nothing when ``out_dir`` is None."""
    if out_dir is None:
        yield
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out_dir / "log.txt", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.setLevel(logging.INFO)
    logger = logging.getLogger("reconstructor")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        (out_dir / "config.toml").write_text(cfg.to_toml())
        if calibration is not None:  # at the session's size, so sensors render at it by name
            calibration_at(calibration, ts.resolution).write(out_dir / "calibration.toml")
        yield
    finally:
        logger.removeHandler(handler)
        handler.close()


def _log_start(ts: Timestamp) -> None:
    missing = ", ".join(f"SN{s}" for s in ts.missing_serials)
    log.info(
        "reconstructing %s at set %d (t = %.3f s) from %d sensors%s",
        ts.session,
        ts.set_index,
        ts.t_s,
        len(ts.frames),
        f"; missing cameras {missing}" if missing else "",
    )


def _init_gaussians(
    fused: FusedCloud,
    train_views: Sequence[View],
    bounds: Bounds | None,
    cfg: ReconstructConfig,
) -> Gaussians:
    """The initial Gaussians: from the fused cloud's points, or uniform in a box for
    ``init_method = "random"`` (the fused cloud is still made: points.ply and the
    depth-reprojection baseline need it)."""
    if cfg.init_method == "random":
        lo, hi = random_init_box(train_views, bounds)
        return init_random(cfg.random_init_count, lo, hi, cfg.init, seed=cfg.train.seed)
    return init_from_points(fused.points_m, fused.colours, cfg.init)


@dataclass
class _Refinement:
    """What the refinement stage trains on: ``views`` (the inputs first), per-view loss
    ``weights`` (None: all 1) and the summary's ``auxiliary`` entry."""

    views: Sequence[View]
    weights: list[float] | None
    summary: dict[str, Any]
    eye_views: Sequence[View] = ()  # trained as a group of their own (auxiliary.eye.share)


def _auxiliary_stage(
    trainer: Trainer,
    train_views: list[View],
    cfg: ReconstructConfig,
    refiner: Refiner | None,
    refine: RefineHook | None,
    bounds: Bounds | None,
    out_dir: Path | None,
    timings: dict[str, float],
) -> _Refinement:
    """The views of the refinement stage: the caller's hook's, the input views plus the
    refiner's auxiliary views, or the input views alone."""
    if refine is not None and cfg.train.refine_steps > 0:
        with _timed(timings, "auxiliary_views"):
            views = refine(trainer, train_views)
        summary = {"enabled": True, "refiner": "caller's refine hook"}
        summary["views"] = len(views) - len(train_views)
        return _Refinement(views, None, summary)
    if refiner is None:
        return _Refinement(train_views, None, {"enabled": False})
    parts: dict[str, float] = {}
    sheet = (
        out_dir / "auxiliary_views.jpg"
        if out_dir is not None and cfg.auxiliary.save_pictures
        else None
    )
    with _timed(timings, "auxiliary_views"):
        aux_views = make_auxiliary_views(
            trainer.g,
            train_views,
            cfg.auxiliary,
            cfg.raster,
            refiner,
            bounds_m=bounds,
            sheet_path=sheet,
            timings_s=parts,
        )
    summary = {
        "enabled": True,
        "refiner": refiner.describe(),
        "views": len(aux_views),
        "per_input_view": cfg.auxiliary.num_views,
        "radius_m": cfg.auxiliary.radius_m,
        "size_px": [train_views[0].width_px, train_views[0].height_px],
        "seconds": round(timings["auxiliary_views"], 3),
        "render_s": round(parts["render"], 3),
        "refine_s": round(parts["refine"], 3),
    }
    eye_cfg = cfg.auxiliary.eye
    eye_views: list[View] = []
    if eye_cfg.num_views > 0:
        t0 = time.perf_counter()
        eye_views = make_eye_views(
            trainer.g, train_views, eye_cfg, cfg.raster, refiner, bounds_m=bounds
        )
        seconds = time.perf_counter() - t0
        timings["auxiliary_views"] += seconds
        summary["seconds"] = round(timings["auxiliary_views"], 3)
        summary["eye_views"] = {"views": len(eye_views), "seconds": round(seconds, 3)}
    weights = [1.0] * len(train_views) + [cfg.auxiliary.aux_weight] * len(aux_views)
    return _Refinement([*train_views, *aux_views], weights, summary, eye_views)


def _refinement_stage(
    trainer: Trainer,
    train_views: list[View],
    refinement: _Refinement,
    cfg: ReconstructConfig,
    progress: Progress | None,
) -> None:
    """Train on the refinement views: with ``auxiliary.input_share`` > 0 each step draws from
    the input views with that probability, else from all views alike with their weights."""
    share = cfg.auxiliary.input_share
    views = refinement.views
    eyes = list(refinement.eye_views)
    if refinement.weights is not None and share > 0:
        inputs, extra = views[: len(train_views)], views[len(train_views) :]
        to_inputs, to_extra, to_eyes = cfg.auxiliary.refinement_shares(bool(eyes))
        trainer.run_mixed(
            [
                ViewGroup(inputs, to_inputs),
                ViewGroup(extra, to_extra, cfg.auxiliary.aux_weight),
                ViewGroup(eyes, to_eyes, cfg.auxiliary.aux_weight),
            ],
            cfg.train.refine_steps,
            stage="refinement",
            progress=progress,
        )
    else:
        weights = refinement.weights
        if eyes:
            weights = [*(weights or [1.0] * len(views)), *[cfg.auxiliary.aux_weight] * len(eyes)]
        trainer.run(
            [*views, *eyes],
            cfg.train.refine_steps,
            stage="refinement",
            progress=progress,
            weights=weights,
        )


def write_outputs(result: Reconstruction, *, models: bool = True) -> None:
    out = result.out_dir
    assert out is not None
    if models:
        ply.write_ply(out / "splats.ply", result.gaussians)
        ply.write_points_ply(out / "points.ply", result.fused.points_m, result.fused.colours)
    ts = result.timestamp
    summary: dict[str, Any] = {
        "session": str(ts.session),
        "set_index": ts.set_index,
        "set_unix_ns": ts.set_unix_ns,
        "t_s": ts.t_s,
        "sensors": [f.camera.name for f in ts.frames],
        "missing_cameras": [f"SN{s}" for s in ts.missing_serials],
        "damaged_images": list(ts.damaged_images),  # left out: they fail their checksums
        "train_views": [v.name for v in result.train_views],
        "held_out_views": [v.name for v in result.held_out_views],
        "gaussians": result.gaussians.num,
        "init_method": result.config.init_method,
        "auxiliary": result.auxiliary,
        "fusion": result.fused.stats,
        "steps": result.trainer.step_index,
        "final_loss": result.trainer.log.mean_loss(),
        "timings_s": {k: round(v, 3) for k, v in result.timings_s.items()},
        "ms_per_step": _ms_per_step(result),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    if models:
        log.info("wrote %s (%d Gaussians)", out / "splats.ply", result.gaussians.num)


def _ms_per_step(result: Reconstruction) -> dict[str, float]:
    steps = result.trainer.log.steps
    warm = result.config.train.warmup_steps
    out = {}
    for stage, part in (("warm-up", steps[:warm]), ("refinement", steps[warm:])):
        if part:
            out[stage] = round(1000 * float(np.mean([s.seconds for s in part])), 1)
    return out


def _json_default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    return str(v)
