"""One chain of a case's timestamps, run where a worker runs it (this process, a pool process
or a Ray task): read each set from the session on shared storage, reconstruct it, publish its
model atomically, and say what was made. Only the runner writes the index.

A model is published as ``models/<name>.npz`` (``storage.py``: a cold timestamp as a quantised
keyframe, a warm one as its changes since the timestamp before): written
to ``.<name>.<ext>.<pid>.partial`` beside it, fsynced, then renamed, so a reader (and the
index) sees the whole file or none (``protocol.durable.atomic_write_bytes``). Its quaternions are
normalised on the way out: viewers
assume unit length, and training leaves them between about 0.74 and 1.06. The run folder (log,
summary, config) goes to ``runs/<name>/``.

A sealed session's timestamp (``Timestamp.sealing``) is published as ``models/<name>.npz.sealed``
(sealed in memory), its depth cache entry sealed too, and its run folder gets no ``splats.ply``,
``points.ply`` or ``auxiliary_views.jpg``: no plaintext of it is written anywhere.

This module imports torch only inside functions, so a spawned worker can set its thread count
(``limit_threads``) before torch or numba start their pools.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class StepJob:
    name: str
    set_index: int
    warm_from: str = ""  # the name of the timestamp this one starts from ("": cold)


@dataclass(frozen=True, kw_only=True)
class ChainJob:
    """Everything a worker needs, as plain values (it crosses process and machine borders)."""

    case_dir: str
    session: str
    calibration: str
    config_toml: str  # the cold config
    warm_toml: str  # the warm timestamps' config ("" without warm start)
    warm: dict[str, Any] = field(default_factory=dict)  # WarmStartConfig fields
    steps: tuple[StepJob, ...] = ()
    threads: int = 0  # 0: leave torch's and numba's defaults
    depth_cache: str = ""  # a folder keeping each timestamp's depth stage ("": none)
    # the identity file that opens a sealed session ("": none): its path, so the secret key
    # never travels with the job; each worker reads it where the session is read
    identity: str = ""


@dataclass(frozen=True, kw_only=True)
class StepResult:
    name: str
    ok: bool
    model: str = ""
    xxh3_64: str = ""
    bytes: int = 0
    seconds: float = 0.0
    cpu_s: float = 0.0
    gaussians: int = 0
    warm_from: str = ""
    error: str = ""
    counts: dict[str, int] = field(default_factory=dict)


def limit_threads(threads: int) -> None:
    """At most ``threads`` compute threads in this process (torch, numba, OpenMP, BLAS)."""
    if threads <= 0:
        return
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))
    import numba
    import torch

    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]


def run_chain(job: ChainJob, progress: Any = None, on_done: Any = None) -> list[StepResult]:
    """Reconstruct the chain's timestamps in order; a failed one is reported, and the ones
    after it that would start from it start cold instead. ``on_done(result)`` is called after
    each (the in-process runner updates the index there)."""
    limit_threads(job.threads)
    results = []
    previous_failed = ""
    for step in job.steps:
        warm_from = "" if step.warm_from == previous_failed else step.warm_from
        result = run_step(job, step, warm_from, progress)
        previous_failed = "" if result.ok else step.name
        results.append(result)
        if on_done is not None:
            on_done(result)
    return results


def run_step(job: ChainJob, step: StepJob, warm_from: str, progress: Any) -> StepResult:
    from protocol.errors import UserError

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        made = _reconstruct(job, step, warm_from, progress)
    except UserError as exc:
        return StepResult(name=step.name, ok=False, error=str(exc))
    except Exception as exc:  # a bug in one timestamp must not lose the others
        log.exception("timestamp %s failed", step.name)
        return StepResult(name=step.name, ok=False, error=f"{type(exc).__name__}: {exc}")
    return StepResult(
        name=step.name,
        ok=True,
        seconds=round(time.perf_counter() - t0, 3),
        cpu_s=round(time.process_time() - c0, 3),
        warm_from=warm_from,
        **made,
    )


def _reconstruct(job: ChainJob, step: StepJob, warm_from: str, progress: Any) -> dict[str, Any]:
    from protocol.formats.rig_calibration import RigCalibration
    from protocol.sealing import load_identity
    from reconstructor.case import storage
    from reconstructor.case.index import CaseIndex
    from reconstructor.case.warm import WarmStartConfig, seed_from_previous
    from reconstructor.config import ReconstructConfig
    from reconstructor.data.frames import load_timestamp
    from reconstructor.pipeline import reconstruct

    case = Path(job.case_dir)
    calibration = RigCalibration.read(job.calibration)
    identity = load_identity(Path(job.identity)) if job.identity else None
    ts = load_timestamp(job.session, calibration, f"set:{step.set_index}", identity=identity)
    seal = ts.sealing  # a sealed session's: its models and cached depth are sealed too
    init = None
    counts: dict[str, int] = {}
    parent: Any = None  # the previous model as stored, when this one is stored as its changes
    lineage: dict[str, Any] = {}
    if warm_from:
        config = ReconstructConfig.from_toml(job.warm_toml, "the case's warm config")
        # the runner records each timestamp in the index before its follower starts
        entry = CaseIndex.read(case).by_name()[warm_from]
        if storage.is_compact(entry):
            parent = storage.load_stored(
                case, entry.model, entry.xxh3_64, entry.bytes, warm_from, seal
            )
            previous = parent.gaussians()
            lineage["ref"] = {"model": entry.model, "xxh3_64": entry.xxh3_64, "bytes": entry.bytes}
        else:
            previous = storage.load_model(case, entry, seal)
        warm = WarmStartConfig(**job.warm)

        def init(ts_, fused, depths):
            seed = seed_from_previous(previous, ts_, fused, depths, warm, config.init)
            counts.update(seed.counts)
            # which of the previous rows were kept (in order, first): the stored form names them
            lineage["alive"] = seed.alive
            return seed.gaussians
    else:
        config = ReconstructConfig.from_toml(job.config_toml, "the case's config")
    if seal is not None:  # the run folder keeps no picture of the room
        config = dataclasses.replace(
            config, auxiliary=dataclasses.replace(config.auxiliary, save_pictures=False)
        )
    work = case / ".work" / f"{step.name}.{os.getpid()}"
    shutil.rmtree(work, ignore_errors=True)
    from reconstructor.depth.cache import DepthCache
    from reconstructor.depth.evidence import observed_of_reconstruction

    # memory 0: a worker sees each timestamp once; the folder serves reruns and other machines
    cache = DepthCache(Path(job.depth_cache), memory=0) if job.depth_cache else None
    result = reconstruct(
        ts, config, work, calibration=calibration, progress=progress, init=init,
        depth_cache=cache, write_models=seal is None,
    )  # fmt: skip
    rel = f"models/{step.name}{storage.SUFFIX if seal is None else storage.SEALED_SUFFIX}"
    alive = lineage.get("alive")
    if parent is None or alive is None or int(alive.sum()) != counts.get("kept"):
        parent, alive = None, None  # a keyframe, or a chain that cannot be followed
    # with what the stereo pairs saw (not the capped, filled training cloud), for the
    # sterile-field tool and people (depth/evidence.py)
    seen = observed_of_reconstruction(result.depth, ts.stereo_pairs())
    storage.write_model(case / rel, result.gaussians, parent=parent, parent_ref=lineage.get("ref"),
                        alive=alive, points_m=seen.points_m, points_noise=seen.m_per_px,
                        points_seen_by=seen.seen_by, points_cameras=seen.cameras,
                        seal=seal)  # fmt: skip
    model = case / rel
    digest, size = _checksum(model)
    _keep_run_folder(work, case / "runs" / step.name)
    return {
        "model": rel,
        "xxh3_64": digest,
        "bytes": size,
        "gaussians": result.gaussians.num,
        "counts": counts,
    }


def _checksum(path: Path) -> tuple[str, int]:
    from reconstructor.case.index import checksum_file

    return checksum_file(path)


def _keep_run_folder(work: Path, target: Path) -> None:
    """The run's log, summary and config move to ``runs/<name>/``; its splats.ply (the
    published model holds it) and points.ply (the fused cloud, as large again) do not."""
    for name in ("splats.ply", "points.ply"):
        (work / name).unlink(missing_ok=True)
    shutil.rmtree(target, ignore_errors=True)
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(work, target)
