"""The paper's evaluation protocols on an evaluation set (paper, "Evaluation Protocols").

The set (``protocol.formats.eval_set``) says what there is to judge: per scene a session, its
calibration, the sets (instants) to evaluate, consecutive sets for temporal stability and the
reference views. Each protocol takes what the chosen scenes offer:

- **near-field**: for every scene and each of its ``eval_sets``, train on the left images only;
  render the held-out right cameras (12 cm from a trained one) and score them against the
  recorded right images: PSNR, SSIM (+ LPIPS). Mean ± SD over (scene, set).
- **phases** (Table 2): the near-field scores grouped by the scenes' workflow ``phase`` (scenes
  without one are left out).
- **egocentric** (Table 4): models trained on all the sensors at each instant that has
  reference views, rendered at every view's camera and scored against its image (on the
  simulated OR the exact view from a person's eyes; on a site a hand-held camera's frame with a
  registered pose). A scene for the statistics is one (scene, set, view). Scenes without
  views are skipped.
- **temporal** (Table 3B): each scene's ``temporal_sets`` (at least two, consecutive),
  reconstructed independently (left images, as near-field) and rendered from the fixed,
  calibrated right cameras; t-PSNR, t-SSIM, flicker (+ t-LPIPS) over adjacent pairs
  (``temporal.py``). The recorded right images are scored too, as the scene's own change.

A reconstruction is keyed by (scene, set, training views) and serves every protocol that can
use it: near-field and phases share their models, and a temporal sequence's frame at an eval
set is a near-field reconstruction. Stereo and fusion run inside each method's reconstruction;
the depth-reprojection baseline takes the fused cloud of a depth-initialised run of the same
timestamp.

This module plans (which timestamps, for which protocols); ``runner.py`` runs one planned job
and ``run.py`` runs a whole plan.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from protocol.command import CommandArgumentError
from protocol.formats.eval_set import EvalScene, EvalSet, ReferenceView
from reconstructor.evaluation.methods import EvalSettings

log = logging.getLogger(__name__)

HELD_OUT_PROTOCOLS = ("near-field", "phases")
_VIEWS_ORDER = {"left": 0, "all": 1}


@dataclass(frozen=True)
class Scene:
    """One set (instant) of one scene of the evaluation set."""

    name: str  # the evaluation set's scene
    phase: str  # its workflow phase ("" if unknown)
    set_index: int

    @property
    def label(self) -> str:
        return f"{self.name}@set{self.set_index}"


@dataclass
class Job:
    """One timestamp reconstructed once per method, and what each protocol wants from it."""

    scene: Scene
    train_views: str  # "left" (near-field, phases, temporal) or "all" (egocentric)
    held_out_protocols: list[str] = field(default_factory=list)
    temporal: list[tuple[str, int]] = field(default_factory=list)  # (sequence label, frame)
    ego_views: list[ReferenceView] = field(default_factory=list)


def select_scenes(settings: EvalSettings, eval_set: EvalSet) -> list[EvalScene]:
    """The set's scenes that ``--scenes`` and ``--phases`` choose (all by default)."""
    names = [s.name for s in eval_set.scenes]
    phases = list(dict.fromkeys(s.phase for s in eval_set.scenes if s.phase))
    for name in settings.scenes:
        if name not in names:
            raise CommandArgumentError(
                f"--scenes {name}: the evaluation set has no such scene; it has {', '.join(names)}"
            )
    for phase in settings.phases:
        if phase not in phases:
            have = ", ".join(phases) or "none (no scene names its phase)"
            raise CommandArgumentError(
                f"--phases {phase}: no scene of the evaluation set shows it; its phases: {have}"
            )
    chosen = [
        s
        for s in eval_set.scenes
        if (not settings.scenes or s.name in settings.scenes)
        and (not settings.phases or s.phase in settings.phases)
    ]
    if not chosen:
        raise CommandArgumentError(
            f"--scenes {' '.join(settings.scenes)} --phases {' '.join(settings.phases)}: "
            "no scene is both; choose one of them"
        )
    return chosen


def plan(settings: EvalSettings, eval_set: EvalSet) -> list[Job]:
    """The reconstructions the chosen protocols need, each once, in the order they run: scene
    by scene and set by set, so a timestamp is read once for all its jobs."""
    scenes = select_scenes(settings, eval_set)
    jobs: dict[tuple[str, int, str], Job] = {}

    def job(scene: EvalScene, set_index: int, train_views: str) -> Job:
        key = (scene.name, set_index, train_views)
        if key not in jobs:
            jobs[key] = Job(Scene(scene.name, scene.phase, set_index), train_views)
        return jobs[key]

    def need(protocol: str, found: list[EvalScene], what: str) -> None:
        if protocol in settings.protocols and not found:
            chosen = ", ".join(s.name for s in scenes)
            raise CommandArgumentError(
                f"--protocol {protocol}: no chosen scene of the evaluation set ({chosen}) has "
                f"{what}; choose another protocol or scene, or add them to the set "
                "(docs/evaluation.md)"
            )

    with_sets = [s for s in scenes if s.eval_sets]
    need("near-field", with_sets, "eval_sets")
    need("phases", [s for s in with_sets if s.phase], "both eval_sets and a phase")
    for protocol in HELD_OUT_PROTOCOLS:
        if protocol not in settings.protocols:
            continue
        for s in with_sets:
            if protocol == "phases" and not s.phase:
                log.warning("scene %s names no phase: the phases protocol leaves it out", s.name)
                continue
            for k in s.eval_sets:
                job(s, k, "left").held_out_protocols.append(protocol)
    if "temporal" in settings.protocols:
        sequences = [s for s in scenes if len(s.temporal_sets) >= 2]
        need("temporal", sequences, "at least two temporal_sets")
        for s in sequences:
            label = f"{s.name}@set{s.temporal_sets[0]}"
            for frame, k in enumerate(s.temporal_sets):
                job(s, k, "left").temporal.append((label, frame))
    if "egocentric" in settings.protocols:
        peopled = [s for s in scenes if s.views]
        need("egocentric", peopled, "reference views")
        for s in scenes:
            if not s.views:
                log.info(
                    "scene %s has no reference views: the egocentric protocol skips it", s.name
                )
            for v in s.views:
                job(s, v.set_index, "all").ego_views.append(v)
    order = {s.name: i for i, s in enumerate(scenes)}
    return sorted(
        jobs.values(),
        key=lambda j: (order[j.scene.name], j.scene.set_index, _VIEWS_ORDER[j.train_views]),
    )
