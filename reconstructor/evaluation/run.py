"""Running a whole evaluation plan: check it against the sessions, then run every job.

``plan.py`` makes the plan, ``runner.py`` runs one job; this module is the only one that needs
both, so the imports run one way (plan <- runner <- run).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from protocol.formats.eval_set import EvalSet, EvalSetError
from reconstructor.depth.cache import DepthCache
from reconstructor.evaluation.lpips import Lpips
from reconstructor.evaluation.methods import METHODS, EvalSettings
from reconstructor.evaluation.plan import Job, plan
from reconstructor.evaluation.records import JobRecords
from reconstructor.evaluation.runner import EvalSource, JobRunner
from reconstructor.evaluation.tables import EvalResults

log = logging.getLogger(__name__)


def check_plan(jobs: list[Job], source: EvalSource) -> None:
    """Every planned set must exist in its session, and every calibration must fit its
    session: a bad evaluation set fails here, before hours of work, not at its turn."""
    highest: dict[str, int] = {}
    for j in jobs:
        highest[j.scene.name] = max(highest.get(j.scene.name, -1), j.scene.set_index)
    for name, k in highest.items():
        count = source.set_count(name)
        if k >= count:
            raise EvalSetError(
                f"{source.eval_set.root}: scene '{name}' asks for set {k} but its session "
                f"{source.scene(name).session} holds {count} sets (0 to {count - 1})"
            )


def run_evaluation(
    settings: EvalSettings,
    eval_set: EvalSet,
    out_dir: Path,
    lpips_model: Lpips | None = None,
    jobs: list[Job] | None = None,
    source: EvalSource | None = None,
    depth_cache: DepthCache | None = None,
    records: JobRecords | None = None,
) -> EvalResults:
    """Run every planned reconstruction (``plan(settings, eval_set)`` unless given), score it
    for each protocol, and return the scores. Each timestamp's depth stage is made once for all
    its rows (in ``depth_cache``, which may keep it on disk too). With ``records``, each
    finished job is written there and a job already recorded is loaded, not run again."""
    jobs = plan(settings, eval_set) if jobs is None else jobs
    source = EvalSource(eval_set) if source is None else source
    trained = [m for m in settings.methods if METHODS[m].trained]
    depth_only = "depth-reprojection" in settings.methods and not any(
        METHODS[m].depth_init for m in trained
    )
    # every recorded job read now, once: a damaged record stops the run before any work
    recorded = {} if records is None else {id(j): r for j in jobs if (r := records.load(j))}
    units = (len(jobs) - len(recorded)) * (len(trained) + (1 if depth_only else 0))
    if recorded:
        log.info("resuming: %d of %d timestamp(s) recorded already", len(recorded), len(jobs))
    log.info(
        "evaluation plan: %d timestamp(s), %d reconstruction(s) to run (%s); %s",
        len(jobs),
        units,
        ", ".join(settings.protocols),
        settings.describe(),
    )
    for key in settings.methods:
        if key in METHODS and settings.auxiliary_steps(key) == 0:
            log.warning(
                "%s trains on none of its refiner's views at --steps %d: the recorded views keep "
                "their share of the %d refinement steps, so its numbers are those of training on "
                "the recorded views alone; give --steps %d or more for the refiner to count",
                settings.label(key),
                settings.steps,
                settings.refine_steps,
                settings.steps_for_auxiliary(key),
            )
    results = EvalResults(settings=settings)
    runner = JobRunner(
        settings,
        source,
        out_dir,
        results,
        lpips_model,
        total_units=units,
        depth_cache=depth_cache if depth_cache is not None else DepthCache(),
        records=records,
    )
    for job in jobs:
        runner.run(job, recorded.get(id(job)))
    runner.finish_temporal()
    cache = runner.depth_cache
    log.info("depth stage: %d computed, %d reused", cache.misses, cache.hits)
    if len(results.depth_made_by) > 1:
        log.warning(
            "the jobs' depth stages were made by different libraries: %s; another OpenCV gives "
            "other depths: for one version, run again with a new --depth-cache and --out",
            "; ".join(f"{k} ({n} jobs)" for k, n in results.depth_made_by.items()),
        )
    results.wall_s = time.perf_counter() - runner.started + runner.resumed_s
    results.resumed_jobs = runner.resumed
    return results
