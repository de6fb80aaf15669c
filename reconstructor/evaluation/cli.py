"""``egosurg evaluate``: the paper's evaluation protocols on an evaluation set.

Reconstructs the set's timestamps with each method of the paper's Tables 3/4 (depth
reprojection, image-only 3DGS, EgoSurg w/o refinement, EgoSurg) and scores them against the
held-out right cameras and the set's reference views. The set is read through
``protocol.formats.eval_set``: ``egosurg sim eval-set`` writes one for the simulated OR, with
the exact view from each person's eyes; a site writes its point-of-view recordings with registered
poses
in the same format. See docs/evaluation.md for the protocols and metrics.

Examples::

    # the simulated OR's evaluation set, then every protocol with the Markdown report
    egosurg sim eval-set --out evalset/
    egosurg evaluate evalset/ --out eval/ --protocol all --write-doc EVALUATION.md

    # a quick look (minutes): one scene, few steps, small images
    egosurg evaluate evalset/ --out eval/ --scenes intraoperative --steps 40 --train-width 240

``--steps`` is the total per reconstruction, 25 % warm-up and 75 % refinement (the paper:
500 + 1500); with LPIPS add ``--lpips-weights ~/weights/alexnet-owt-7be5be79.pth``. The set
decides what is evaluated: near-field and phases use each scene's eval sets, egocentric its
reference views, temporal its consecutive sets; ``--scenes`` and ``--phases`` choose scenes.
Outputs in OUT: ``<protocol>/table.md|table.csv|scores.csv|png/``, ``summary.md``,
``settings.json``, each method's resolved config in ``configs/`` and each finished
timestamp's record in ``jobs/``: a run that stopped (killed, machine given back) continues
with the same command and ``--resume``, running only what it had not finished.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shlex
import time
from pathlib import Path

from protocol.command import CommandArgumentError, command_parser
from protocol.formats.eval_set import EvalSet
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from reconstructor.case.warm import WarmStartConfig
from reconstructor.evaluation.methods import (
    METHODS,
    PAPER_ORDER,
    PROTOCOLS,
    EvalSettings,
)
from reconstructor.raster.device import add_device_option, check_device

log = logging.getLogger(__name__)

TITLES = {
    "near-field": "Near-field fidelity (held-out right cameras)",
    "phases": "Near-field fidelity per workflow phase",
    "egocentric": "Egocentric views against the set's reference views",
    "temporal": "Temporal stability (fixed right cameras)",
}


def _names(values: list[str]) -> tuple[str, ...]:
    """``a b`` and ``a,b`` both name two items."""
    return tuple(dict.fromkeys(v for item in values for v in item.split(",") if v))


def build_parser() -> argparse.ArgumentParser:
    p = command_parser("egosurg evaluate", __doc__)
    p.add_argument("eval_set", metavar="EVALSET", help="the evaluation set's folder (or manifest)")
    add_identity_argument(p)  # the scenes' sessions
    p.add_argument("--out", required=True, help="folder for the tables and pictures")
    p.add_argument(
        "--protocol",
        nargs="+",
        default=["near-field"],
        choices=(*PROTOCOLS, "all"),
        help="one or more (default near-field)",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        default=list(PAPER_ORDER),
        help=f"any of {', '.join(METHODS)} (default: the paper's {', '.join(PAPER_ORDER)})",
    )
    p.add_argument(
        "--warm-steps",
        type=int,
        default=WarmStartConfig.steps,
        help="egosurg-warm: training steps of each later frame (default %(default)s)",
    )
    p.add_argument("--scenes", nargs="+", default=[], help="the set's scenes to use (all)")
    p.add_argument("--phases", nargs="+", default=[], help="use the scenes of these phases (all)")
    p.add_argument("--steps", type=int, default=2000, help="training steps per reconstruction")
    add_device_option(p, "the --config's [raster] backend, the CPU's numba kernels")
    p.add_argument("--train-width", type=int, default=960, help="training image width, px")
    p.add_argument("--refiner", default="guided", help="EgoSurg's refiner: guided, difix, none")
    p.add_argument("--refiner-weights", default="", help="local weights for the refiner")
    p.add_argument("--lpips-weights", default="", help="torchvision AlexNet/VGG16 weights (.pth)")
    p.add_argument(
        "--config", default="", help="reconstruction config (TOML) every method starts from"
    )
    p.add_argument("--write-doc", help="also write this Markdown report (e.g. EVALUATION.md)")
    p.add_argument(
        "--depth-cache",
        default="",
        help="keep each timestamp's stereo depth and fused cloud in this folder and reuse them "
        "(a rerun, or a machine without OpenCV contrib or open3d, skips that stage)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue a stopped run in the same --out: load each job it finished (OUT/jobs/) "
        "and run the rest, with the same options",
    )
    return p


def settings_from_args(args: argparse.Namespace) -> EvalSettings:
    chosen = set(args.protocol)
    protocols = PROTOCOLS if "all" in chosen else tuple(p for p in PROTOCOLS if p in chosen)
    methods = _names(args.methods)
    # the paper's row order, whatever order they were given in
    ordered = tuple(m for m in METHODS if m in methods) + tuple(
        m for m in methods if m not in METHODS
    )
    return EvalSettings(
        eval_set=args.eval_set,
        protocols=protocols,
        methods=ordered,
        warm_steps=args.warm_steps,
        scenes=_names(args.scenes),
        phases=_names(args.phases),
        steps=args.steps,
        train_width_px=args.train_width,
        refiner=args.refiner,
        refiner_weights=args.refiner_weights,
        lpips_weights=args.lpips_weights,
        config=args.config,
        device=args.device or "",
    )


def _check_refiner(settings: EvalSettings) -> None:
    """Load EgoSurg's refiner once now: a bad name or weights path fails before any work."""
    if not settings.uses_refiner:
        return
    from reconstructor.pipeline import build_refiner
    from reconstructor.refine.auxiliary import AuxiliaryConfig

    build_refiner(
        AuxiliaryConfig(refiner=settings.refiner, refiner_weights=settings.refiner_weights)
    )


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    settings = settings_from_args(args)
    if not args.resume:  # a resume may have nothing left to run: checked once its records are read
        check_device(settings.device or None)  # no GPU: one line now, before any work
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CommandArgumentError(f"--out {out} is a file; give a folder")
    if settings.config:
        from reconstructor.config import ReconstructConfig

        ReconstructConfig.read(settings.config)  # a bad file fails now, with its key named
    eval_set = EvalSet.read(args.eval_set)  # EvalSetError: one line naming what is wrong
    settings = dataclasses.replace(settings, eval_set_description=eval_set.description)
    from reconstructor.evaluation.doc import depth_makers_line, write_evaluation_doc
    from reconstructor.evaluation.lpips import load_lpips
    from reconstructor.evaluation.plan import plan
    from reconstructor.evaluation.run import check_plan, run_evaluation
    from reconstructor.evaluation.runner import EvalSource
    from reconstructor.evaluation.tables import write_protocol

    lpips_model = load_lpips(settings.lpips_weights) if settings.lpips_weights else None
    _check_refiner(settings)
    # before anything is written: a plan that cannot work, or a set that lacks what it needs,
    # fails here
    jobs = plan(settings, eval_set)
    source = EvalSource(eval_set, identity_from_args(args))
    check_plan(jobs, source)
    from reconstructor.depth.cache import DepthCache

    depth_cache = DepthCache(Path(args.depth_cache) if args.depth_cache else None)
    from reconstructor.evaluation.records import JobRecords

    records = JobRecords(out, settings)
    records.check_start(args.resume)  # an earlier run's work is never overwritten
    if args.resume and records.missing(jobs):
        check_device(settings.device or None)  # work is left: the device it needs, before it
    elif args.resume and settings.device:
        # a run made elsewhere (a GPU server's jobs/ copied here): only the tables are left
        log.info(
            "every job is recorded: writing the tables, nothing runs on --device %s",
            settings.device,
        )
    out.mkdir(parents=True, exist_ok=True)

    command = "egosurg evaluate " + shlex.join(argv)
    (out / "settings.json").write_text(
        json.dumps({"command": command, **settings.as_dict()}, indent=2) + "\n"
    )
    t0 = time.perf_counter()
    results = run_evaluation(
        settings, eval_set, out, lpips_model, jobs, source, depth_cache, records
    )
    parts = [
        f"# EgoSurg evaluation\n\nEvaluation set: `{eval_set.root}` ({eval_set.description})\n\n"
        f"Command: `{command}`\n\n{depth_makers_line(results)}\n"
    ]
    for protocol in settings.protocols:
        parts.append(write_protocol(results, protocol, out / protocol, TITLES[protocol]))
    summary = "\n".join(parts)
    (out / "summary.md").write_text(summary)
    print(summary)
    if args.write_doc:
        write_evaluation_doc(results, eval_set, Path(args.write_doc), command)
        print(f"wrote {args.write_doc}")
    print(f"evaluation done in {time.perf_counter() - t0:.0f} s; tables in {out}")
    return 0
