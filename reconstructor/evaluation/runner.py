"""Running one planned timestamp of an evaluation: read it from the evaluation set,
reconstruct it once per method, render every target the protocols asked for, score the
renders, and keep temporal frames for later.

The warm-start row (``egosurg-warm``) carries a model from one frame of a temporal sequence to
the next: the sequence's first frame reuses EgoSurg's cold model of the same run (or trains it,
if EgoSurg is not among the methods); each later frame is warm-started from the row's model of
the frame before (``reconstructor/case/warm.py``), so its time is the warm timestamp's alone.

Progress: one log line per reconstruction with its time, the elapsed time and an ETA from the
mean time per reconstruction so far (the first timestamp also pays for compiling kernels, so
the first ETA is pessimistic).
"""

from __future__ import annotations

import itertools
import logging
import time
from pathlib import Path

import numpy as np

from protocol.formats.eval_set import EvalScene, EvalSet, ReferenceView
from protocol.formats.rig_calibration import RigCalibration
from protocol.sealing import Identity
from protocol.session import SessionReader
from reconstructor.case.warm import WarmStartConfig, seed_from_previous, warm_config
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import Timestamp, check_calibration, load_timestamp
from reconstructor.data.views import EYE_NEAR_M, View, novel_view
from reconstructor.depth.cache import DepthCache, DepthStage, describe_made_by
from reconstructor.depth.fusion import fuse
from reconstructor.depth.stereo import DepthMap
from reconstructor.evaluation.baselines import hole_fraction
from reconstructor.evaluation.lpips import Lpips
from reconstructor.evaluation.methods import (
    METHODS,
    EvalSettings,
    method_config,
    render_depth_maps,
    render_splats,
)
from reconstructor.evaluation.metrics import psnr, ssim_value
from reconstructor.evaluation.plan import Job
from reconstructor.evaluation.records import JobRecord, JobRecords
from reconstructor.evaluation.tables import (
    FIDELITY,
    RECORDED,
    EvalResults,
    ImageScore,
    TemporalScore,
    filmstrip,
    side_by_side,
)
from reconstructor.evaluation.temporal import temporal_scores
from reconstructor.pipeline import make_views, reconstruct, stereo_clouds
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)

FILMSTRIP_TILE_PX = 240


class EvalSource:
    """What a run reads from the evaluation set, each file once: every scene's calibration for
    the whole run, and the last timestamp read (the plan runs a timestamp's jobs one after
    another; keeping more would hold ~15 MB of images per timestamp)."""

    def __init__(self, eval_set: EvalSet, identity: Identity | None = None) -> None:
        self.eval_set = eval_set
        self.identity = identity  # opens the scenes' sessions when they are sealed
        self._scenes = {s.name: s for s in eval_set.scenes}
        self._calibrations: dict[str, RigCalibration] = {}
        self._last: tuple[tuple[str, int], Timestamp] | None = None

    def scene(self, name: str) -> EvalScene:
        return self._scenes[name]

    def calibration(self, name: str) -> RigCalibration:
        if name not in self._calibrations:
            path = self.eval_set.path(self.scene(name).calibration)
            self._calibrations[name] = RigCalibration.read(path)
        return self._calibrations[name]

    def set_count(self, name: str) -> int:
        """The number of sets in the scene's session, after checking its calibration fits."""
        scene = self.scene(name)
        with SessionReader(self.eval_set.path(scene.session), identity=self.identity) as reader:
            reader.require_identity(f"scene {name}'s images")
            check_calibration(reader.info, self.calibration(name), scene.calibration)
            return len(reader.sets().set_unix_ns)

    def timestamp(self, name: str, set_index: int) -> Timestamp:
        key = (name, set_index)
        if self._last is None or self._last[0] != key:
            scene = self.scene(name)
            ts = load_timestamp(
                self.eval_set.path(scene.session),
                self.calibration(name),
                f"set:{set_index}",
                calibration_source=str(self.eval_set.path(scene.calibration)),
                identity=self.identity,
            )
            self._last = (key, ts)
        return self._last[1]

    def image(self, view: ReferenceView) -> np.ndarray:
        return self.eval_set.image(view)


def _clock(seconds: float) -> str:
    s = round(seconds)
    return (
        f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s"
        if s >= 3600
        else f"{s // 60}m{s % 60:02d}s"
    )


def _file_name(label: str) -> str:
    """A PNG name for a label like ``intraoperative@set0_SN123-right`` (scene names are free
    text in the set's manifest)."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in label.replace("@", "_"))
    return f"{safe}.png"


def _distinct(made_by: list[dict[str, str]]) -> list[dict[str, str]]:
    """Each different ``made_by`` once, in the order first seen."""
    out: list[dict[str, str]] = []
    for m in made_by:
        if m not in out:
            out.append(dict(m))
    return out


def _u8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)


class JobRunner:
    def __init__(
        self,
        settings: EvalSettings,
        source: EvalSource,
        out_dir: Path,
        results: EvalResults,
        lpips_model: Lpips | None,
        *,
        total_units: int,
        depth_cache: DepthCache | None = None,
        records: JobRecords | None = None,
    ) -> None:
        self.settings = settings
        self.source = source
        self.out_dir = out_dir
        self.results = results
        self.lpips = lpips_model
        self.total = total_units
        # each timestamp's stereo depth and fused cloud, made once for all its rows
        self.depth_cache = depth_cache if depth_cache is not None else DepthCache()
        self.records = records  # where each finished job is written (a stopped run resumes)
        self.resumed = 0  # jobs loaded from their records
        self.resumed_s = 0.0  # the time those jobs took when they ran
        self.done = 0
        self.started = time.perf_counter()
        # (sequence, camera, method) -> frame index -> uint8 render
        self.frames: dict[tuple[str, str, str], dict[int, np.ndarray]] = {}
        self.sequence_phase: dict[str, str] = {}
        # sequence -> (frame, model): the warm row's chain, its last frame's Gaussians
        self.warm_chain: dict[str, tuple[int, Gaussians]] = {}

    def _tick(self, what: str, job: Job, seconds: float) -> None:
        self.done += 1
        elapsed = time.perf_counter() - self.started
        eta = elapsed / self.done * (self.total - self.done)
        log.info(
            "[%d/%d] %s at %s (%s views): %.1f s; elapsed %s, ETA %s",
            self.done,
            self.total,
            what,
            job.scene.label,
            job.train_views,
            seconds,
            _clock(elapsed),
            _clock(eta),
        )

    def _save_config(self, name: str, text: str) -> None:
        """A method's resolved config, as a reconstruction run saves it (the first scene's,
        when the scenes' room bounds differ)."""
        path = self.out_dir / "configs" / f"{name}.toml"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)

    def run(self, job: Job, record: JobRecord | None = None) -> None:
        """Run ``job``, or take its ``record`` from an earlier sitting of this run."""
        if record is not None:
            self._apply(record)
            self.resumed += 1
            self.resumed_s += record.seconds
            log.info("%s (%s views): resumed from its record", job.scene.label, job.train_views)
            return
        t0 = time.perf_counter()
        served_before = len(self.depth_cache.served)
        scores_before = len(self.results.image_scores)
        seconds_before = {k: len(v) for k, v in self.results.recon_seconds.items()}
        refiner_before = self.results.refiner
        self._run(job)
        made_by = _distinct(self.depth_cache.served[served_before:])
        self._count_depth_makers(made_by)
        if self.records is not None:
            record = JobRecord(
                depth_made_by=made_by,
                image_scores=self.results.image_scores[scores_before:],
                recon_seconds={
                    k: v[seconds_before.get(k, 0) :]
                    for k, v in self.results.recon_seconds.items()
                    if len(v) > seconds_before.get(k, 0)
                },
                refiner=self.results.refiner if self.results.refiner != refiner_before else "",
                seconds=time.perf_counter() - t0,
            )
            for sequence, k in job.temporal:
                record.sequence_phase[sequence] = self.sequence_phase[sequence]
                for (seq, view, method), by_frame in self.frames.items():
                    if seq == sequence and k in by_frame:
                        record.frames[(seq, view, method, k)] = by_frame[k]
                chain = self.warm_chain.get(sequence)
                if chain is not None and chain[0] == k:
                    record.warm = (sequence, k, chain[1])
            self.records.save(job, record)

    def _count_depth_makers(self, made_by: list[dict[str, str]] | None) -> None:
        for m in [{}] if made_by is None else made_by:  # None: a record from before they were kept
            said = describe_made_by(m)
            self.results.depth_made_by[said] = self.results.depth_made_by.get(said, 0) + 1

    def _apply(self, record: JobRecord) -> None:
        """Put a recorded job's results where running it would have put them."""
        self._count_depth_makers(record.depth_made_by)
        self.results.image_scores.extend(record.image_scores)
        for name, seconds in record.recon_seconds.items():
            self.results.recon_seconds.setdefault(name, []).extend(seconds)
        if record.refiner:
            self.results.refiner = record.refiner
        for (seq, view, method, k), frame in record.frames.items():
            self.frames.setdefault((seq, view, method), {})[k] = frame
        self.sequence_phase.update(record.sequence_phase)
        if record.warm is not None:
            sequence, k, model = record.warm
            self.warm_chain[sequence] = (k, model)

    def _run(self, job: Job) -> None:
        s, scene = self.settings, job.scene
        ts = self.source.timestamp(scene.name, scene.set_index)
        calibration = self.source.calibration(scene.name)
        bounds = self.source.scene(scene.name).room_bounds_m  # () = unknown: the cameras' box
        probe = method_config(s, "no-refinement", job.train_views, bounds).resolved(
            ts.resolution.width
        )
        held_out = make_views(ts, probe)[1] if job.held_out_protocols or job.temporal else []
        targets: list[View] = [*held_out, *(novel_view(v.camera) for v in job.ego_views)]
        # an egocentric view is seen from a person's eye: their own head is left out
        near = [0.0] * len(held_out) + [EYE_NEAR_M] * len(job.ego_views)

        renders: dict[str, list[np.ndarray]] = {}
        self._holes: dict[str, list[np.ndarray]] = {}  # per method that leaves holes, per target
        depth_maps = None
        cold_models: dict[str, Gaussians] = {}  # EgoSurg's model, if the warm row starts from it
        trained = [m for m in s.methods if METHODS[m].trained]
        for key in sorted(trained, key=lambda m: METHODS[m].warm):  # the warm row last
            t0 = time.perf_counter()
            cfg = method_config(s, key, job.train_views, bounds)
            self._save_config(
                f"{key}-{job.train_views}", cfg.resolved(ts.resolution.width).to_toml()
            )
            if METHODS[key].warm:
                renders[key], what = self._warm_frame(job, ts, calibration, cfg, cold_models,
                                                      targets, near)  # fmt: skip
                if what == "warm":
                    self.results.recon_seconds.setdefault(key, []).append(time.perf_counter() - t0)
                self._tick(f"{key} ({what})", job, time.perf_counter() - t0)
                continue
            recon = reconstruct(ts, cfg, calibration=calibration, depth_cache=self.depth_cache)
            renders[key] = [
                render_splats(recon.gaussians, cfg.raster, v, n)
                for v, n in zip(targets, near, strict=True)
            ]
            if METHODS[key].depth_init and depth_maps is None:
                depth_maps = recon.depth
            if key == "egosurg":
                self.results.refiner = str(recon.auxiliary.get("refiner", s.refiner))
                if s.has_warm:
                    cold_models[key] = recon.gaussians
            del recon
            seconds = time.perf_counter() - t0
            self.results.recon_seconds.setdefault(key, []).append(seconds)
            self._tick(key, job, seconds)
        if "depth-reprojection" in s.methods:
            if depth_maps is None:
                t0 = time.perf_counter()
                depth_maps = self._depth_maps(ts, probe)
                self._tick("stereo for depth reprojection", job, time.perf_counter() - t0)
            sources = [
                (depth_maps[f"SN{left.camera_serial}"], left.camera.pose)
                for left, _ in ts.stereo_pairs()
            ]
            drawn = [render_depth_maps(sources, v, n) for v, n in zip(targets, near, strict=True)]
            renders["depth-reprojection"] = [image for image, _ in drawn]
            self._holes["depth-reprojection"] = [holes for _, holes in drawn]
        methods = [m for m in s.methods if m in renders]
        self._score_held_out(job, held_out, methods, renders)
        self._score_ego(job, len(held_out), methods, renders)

    def _depth_maps(self, ts: Timestamp, cfg: ReconstructConfig) -> dict[str, DepthMap]:
        """The stereo depth maps of ``ts``: from the depth cache, or made (and kept) now."""
        stage = self.depth_cache.get(ts, cfg)
        if stage is None:
            clouds, depths = stereo_clouds(ts, cfg)
            stage = DepthStage(depths, fuse(clouds, cfg.fusion), clouds)
            self.depth_cache.put(ts, cfg, stage)
        return stage.depths

    def _warm_frame(
        self,
        job: Job,
        ts: Timestamp,
        calibration: RigCalibration,
        cfg: ReconstructConfig,
        cold_models: dict[str, Gaussians],
        targets: list[View],
        near: list[float],
    ) -> tuple[list[np.ndarray], str]:
        """The warm row's renders of this job, and how its model was made ("warm", "cold" or
        "EgoSurg's cold model"). A frame whose previous frame has a warm model starts from it."""
        sequence, frame = job.temporal[0] if job.temporal else ("", 0)
        previous = self.warm_chain.get(sequence)
        if frame > 0 and previous is not None and previous[0] == frame - 1:
            warm = WarmStartConfig(steps=self.settings.warm_steps)
            start = previous[1]

            def init(ts_, fused, depths):
                return seed_from_previous(start, ts_, fused, depths, warm, cfg.init).gaussians

            recon = reconstruct(
                ts,
                warm_config(cfg, warm),
                calibration=calibration,
                init=init,
                depth_cache=self.depth_cache,
            )
            gaussians, what = recon.gaussians, "warm"
            del recon
        elif "egosurg" in cold_models:
            gaussians, what = cold_models["egosurg"], "EgoSurg's cold model"
        else:
            recon = reconstruct(ts, cfg, calibration=calibration, depth_cache=self.depth_cache)
            gaussians, what = recon.gaussians, "cold"
            del recon
        if sequence:
            self.warm_chain[sequence] = (frame, gaussians)
        drawn = [
            render_splats(gaussians, cfg.raster, v, n) for v, n in zip(targets, near, strict=True)
        ]
        return drawn, what

    def _scores(self, img: np.ndarray, truth: np.ndarray, mask: np.ndarray | None) -> tuple:
        lp = None if self.lpips is None else self.lpips.distance(img, truth, mask)
        return psnr(img, truth, mask), ssim_value(img, truth, mask), lp

    def _hole_stats(
        self, method: str, i: int, img: np.ndarray, truth: np.ndarray, mask: np.ndarray | None
    ) -> tuple[float | None, float | None]:
        """(share of the compared pixels left empty, PSNR over the drawn ones), or Nones for a
        method that leaves no holes."""
        holes = self._holes.get(method)
        if holes is None:
            return None, None
        drawn = ~holes[i] if mask is None else mask & ~holes[i]
        return hole_fraction(holes[i], mask), (psnr(img, truth, drawn) if drawn.any() else None)

    def _score_held_out(self, job: Job, views: list[View], methods: list[str], renders) -> None:
        for i, view in enumerate(views):
            truth, mask = view.image.numpy(), view.mask.numpy() > 0.5
            if job.held_out_protocols:
                for m in methods:
                    p, q, lp = self._scores(renders[m][i], truth, mask)
                    for protocol in job.held_out_protocols:
                        self.results.image_scores.append(
                            ImageScore(
                                protocol,
                                m,
                                job.scene.phase,
                                job.scene.label,
                                view.name,
                                p,
                                q,
                                lp,
                                *self._hole_stats(m, i, renders[m][i], truth, mask),
                            )
                        )
                tiles = [
                    ("recorded", truth),
                    *((self.settings.label(m), renders[m][i]) for m in methods),
                ]
                for protocol in job.held_out_protocols:
                    name = _file_name(f"{job.scene.label}_{view.name}")
                    side_by_side(self.out_dir / protocol / "png" / name, tiles)
            if job.temporal:  # how close each frame is to the recording, beside its stability
                for m in methods:
                    p, q, lp = self._scores(renders[m][i], truth, mask)
                    self.results.image_scores.append(
                        ImageScore(
                            FIDELITY,
                            m,
                            job.scene.phase,
                            job.scene.label,
                            view.name,
                            p,
                            q,
                            lp,
                            *self._hole_stats(m, i, renders[m][i], truth, mask),
                        )
                    )
            for sequence, k in job.temporal:
                self.sequence_phase[sequence] = job.scene.phase
                self.frames.setdefault((sequence, view.name, RECORDED), {})[k] = _u8(truth)
                for m in methods:
                    self.frames.setdefault((sequence, view.name, m), {})[k] = _u8(renders[m][i])

    def _score_ego(self, job: Job, offset: int, methods: list[str], renders) -> None:
        for i, view in enumerate(job.ego_views):
            truth = self.source.image(view).astype(np.float32) / 255.0
            scene = f"{job.scene.label}/{view.name}"
            tiles = [(f"reference ({view.role or view.name})", truth)]
            for m in methods:
                img = renders[m][offset + i]
                p, q, lp = self._scores(img, truth, None)
                self.results.image_scores.append(
                    ImageScore(
                        "egocentric",
                        m,
                        job.scene.phase,
                        scene,
                        view.name,
                        p,
                        q,
                        lp,
                        *self._hole_stats(m, offset + i, img, truth, None),
                    )
                )
                tiles.append((self.settings.label(m), img))
            name = _file_name(f"{job.scene.label}_{view.name}")
            side_by_side(self.out_dir / "egocentric" / "png" / name, tiles)

    def finish_temporal(self) -> None:
        """Temporal scores of every complete sequence, and one filmstrip per sequence."""
        strips: dict[tuple[str, str], list[tuple[str, list[np.ndarray]]]] = {}
        for (sequence, view, method), by_frame in self.frames.items():
            frames = [by_frame[k] for k in sorted(by_frame)]
            sc = temporal_scores(frames)
            t_lpips = None
            if self.lpips is not None:
                pairs = itertools.pairwise(frames)
                t_lpips = float(np.mean([self.lpips.distance(a, b) for a, b in pairs]))
            self.results.temporal_scores.append(
                TemporalScore(
                    method,
                    self.sequence_phase[sequence],
                    f"{sequence} {view}",
                    view,
                    sc.t_psnr_db,
                    sc.t_ssim,
                    t_lpips,
                    sc.flicker,
                    sc.pairs,
                )
            )
            strips.setdefault((sequence, view), []).append(
                (self.settings.label(method) if method != RECORDED else "recorded", frames)
            )
        shown: set[str] = set()
        for (sequence, view), rows in strips.items():
            if sequence in shown:  # one camera per sequence is enough to see flicker
                continue
            shown.add(sequence)
            width = min(FILMSTRIP_TILE_PX, rows[0][1][0].shape[1])
            name = _file_name(f"{sequence}_{view}")
            filmstrip(self.out_dir / "temporal" / "png" / name, rows, width)
        self.frames.clear()
