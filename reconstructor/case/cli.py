"""``egosurg reconstruct ... --every`` (a whole case) and ``egosurg case info|export``.

Examples::

    egosurg reconstruct CASE.h5 --calibration calibration.toml --every 1s --out case/
    egosurg reconstruct CASE.h5 --from 60 --to 120 --every 0.5s --out case/ --workers 2
    egosurg reconstruct CASE.h5 --every 1s --out case/ --ray auto
    egosurg reconstruct CASE.h5 --every 1s --out case/ --cold     # no warm start
    egosurg case info case/
    egosurg case info case/ --verify    # also read every model and compare its checksum
    egosurg case export case/ --out ply/ [--at t00060.000] [--format splat]
    egosurg case export case/ --out ply/ --identity site.identity   # a sealed session's case

Rerunning the same ``reconstruct`` command resumes: finished timestamps are checked by checksum
and skipped; the rest are (re)done. docs/case.md describes the folder and its index.

``case info`` checks every done model: that its file is there with the size written (always: a
stat per model) and, with ``--verify``, its checksum (reading every model). A missing or damaged
model is shown as MISSING or DAMAGED, not done, and the command exits 1; a model from before
checksums were recorded is "unchecked".

A sealed session's case (docs/case.md, "Sealed cases") keeps its models sealed for the
session's recipients: ``case info`` and ``--verify`` need no key (the checksums are over the
sealed bytes); ``case export`` opens them with ``--identity FILE`` (or ``$EGOSURG_IDENTITY``)
and says where it wrote the plaintext copies.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from protocol.command import add_subcommand, command_parser
from protocol.private_files import make_owner_only, plaintext_notice
from protocol.sealing import Identity
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from protocol.session import SessionReader
from protocol.session.derived import derived_seal, sealing_record
from reconstructor.case.index import INDEX_NAME, CaseIndex, Entry, check_model
from reconstructor.case.plan import (
    config_hash,
    parse_duration_s,
    plan_timestamps,
    session_times,
)
from reconstructor.case.runner import CaseRequest, run_case
from reconstructor.case.warm import WarmStartConfig, warm_config
from reconstructor.config import ReconstructConfig
from reconstructor.errors import CaseFolderError


def reconstruct_case(
    args: argparse.Namespace,
    session: Path,
    cal_path: Path,
    config: ReconstructConfig,
    identity: Identity | None = None,
) -> int:
    """The ``--every`` form of ``egosurg reconstruct``; a sealed session is read with
    ``identity`` (each worker loads it from its file)."""
    with SessionReader(session, identity=identity) as reader:  # refused now, not per timestamp
        reader.require_identity("every image")
        seal = derived_seal(reader, identity)  # its models are sealed for its recipients
    every_s = parse_duration_s(args.every)
    times = session_times(session)
    planned = plan_timestamps(times, every_s, args.from_s, args.to_s)
    if args.workers < 1:
        raise CaseFolderError(f"--workers {args.workers}: give 1 or more processes")
    warm_toml, warm_fields = "", {}
    if not args.cold:  # warm start is the default (it won on time and quality: EVALUATION.md)
        warm = WarmStartConfig(
            steps=args.warm_steps or WarmStartConfig.steps,
            keyframe_every=args.keyframe_every or WarmStartConfig.keyframe_every,
        )
        warm_toml = warm_config(config, warm).to_toml()
        warm_fields = dataclasses.asdict(warm)
    calibration_text = cal_path.read_text()
    req = CaseRequest(
        case_dir=Path(args.out),
        session=session.resolve(),
        session_started_unix_ns=times.started_unix_ns,
        calibration_text=calibration_text,
        config_toml=config.to_toml(),
        warm_toml=warm_toml,
        warm=warm_fields,
        config_hash=config_hash(config.to_toml(), calibration_text, warm_toml),
        planned=tuple(planned),
        workers=args.workers,
        ray=args.ray or "",
        gpus_per_task=1 if config.raster.device == "cuda" else 0,
        force=args.force,
        depth_cache=str(Path(args.depth_cache).resolve()) if args.depth_cache else "",
        identity=str(identity.path.resolve()) if identity and identity.path else "",
        sealing=sealing_record(seal) if seal is not None else None,
    )
    index = run_case(req, step_progress=_StepBar() if args.workers <= 1 and not args.ray else None)
    print(summary_line(req.case_dir, index))
    failed = [e for e in index.timestamps if e.status == "failed"]
    for e in failed:
        print(f"{e.name}: failed: {e.error}", file=sys.stderr)
    return 1 if failed else 0


class _StepBar:
    """A second progress bar over the steps of the timestamp being trained (one worker)."""

    def __init__(self) -> None:
        self.bar: Any = None
        self.stage = ""

    def __call__(self, stage: str, k: int, n: int, stats: Any) -> None:
        from tqdm import tqdm

        if self.bar is None or stage != self.stage:
            if self.bar is not None:
                self.bar.close()
            self.bar = tqdm(total=n, desc=stage, unit="step", position=1, leave=False)
            self.stage = stage
        self.bar.update(k - self.bar.n)
        self.bar.set_postfix(loss=f"{stats.loss:.4f}", refresh=False)
        if k == n:
            self.bar.close()
            self.bar = None


def summary_line(folder: Path, index: CaseIndex) -> str:
    c = index.counts()
    size = sum(e.bytes for e in index.timestamps if e.status == "done")
    return (
        f"{folder}: {c['done']} done, {c['pending']} pending, {c['failed']} failed; "
        f"{size / 1e6:.1f} MB of models"
    )


def info(folder: Path, *, verify: bool = False) -> tuple[str, int]:
    """The case's summary and per-timestamp table, and how many done models are missing or
    damaged (see the module docstring)."""
    index = _read(folder)
    c = index.counts()
    done = [e for e in index.timestamps if e.status == "done"]
    checks = {e.name: check_model(folder, e, read=verify) for e in done}
    lines = [
        f"case {folder}  session {index.session}",
        f"config hash {index.config_hash}  warm start {'on' if index.warm_start else 'off'}",
        f"timestamps {len(index.timestamps)}: {c['done']} done, {c['pending']} pending, "
        f"{c['failed']} failed",
        _checked_line(checks, verify),
    ]
    if index.sealing is not None:  # the recipients are public: no key needed to name them
        from reconstructor.case.sealing import case_seal

        seal = case_seal(folder, index, None)
        assert seal is not None
        lines.append(f"models sealed for {seal.describe()} (open them with --identity)")
    if done:
        from reconstructor.case.storage import is_compact

        total_mb = sum(e.bytes for e in done) / 1e6
        secs = [e.seconds for e in done]
        compact = sum(is_compact(e) for e in done)
        lines.append(
            f"storage: {compact} compact (keyframes quantised, warm ones as changes; "
            "docs/case.md), "
            f"{len(done) - compact} full PLY"
        )
        lines.append(
            f"models {total_mb:.1f} MB ({total_mb / len(done):.2f} MB per timestamp); "
            f"seconds per timestamp: mean {sum(secs) / len(secs):.1f}, min {min(secs):.1f}, "
            f"max {max(secs):.1f}; total {sum(secs):.0f} s"
        )
    lines.append(f"{'name':<12} {'set':>6} {'status':<8} {'MB':>7} {'s':>7} {'gaussians':>9} from")
    for e in index.timestamps:
        lines.append(_entry_line(e, checks.get(e.name)))
    bad = sum(state in ("missing", "damaged") for state, _ in checks.values())
    return "\n".join(lines), bad


def _checked_line(checks: Mapping[str, tuple[str, str]], verify: bool) -> str:
    counts = {k: 0 for k in ("ok", "size ok", "unchecked", "missing", "damaged")}
    for state, _ in checks.values():
        counts[state] += 1
    how = "by checksum" if verify else "by size; --verify reads their checksums"
    return (
        f"models checked {how}: {counts['ok'] + counts['size ok']} as written, "
        f"{counts['missing']} MISSING, {counts['damaged']} DAMAGED, "
        f"{counts['unchecked']} unchecked (no checksum recorded)"
    )


def _entry_line(e: Entry, check: tuple[str, str] | None) -> str:
    status: str = e.status
    note = e.error
    if check is not None and check[0] in ("missing", "damaged", "unchecked"):
        status = check[0].upper() if check[0] != "unchecked" else "done?"
        note = check[1]
    return (
        f"{e.name:<12} {e.set_index:>6} {status:<8} {e.bytes / 1e6:>7.2f} "
        f"{e.seconds:>7.1f} {e.gaussians:>9} {e.warm_from or '-'}" + (f"  {note}" if note else "")
    )


def export(
    folder: Path, out: Path, at: list[str] | None, fmt: str, identity: Identity | None = None
) -> list[Path]:
    """Each done (or each named) timestamp as a standard 3DGS PLY (or .splat) with unit
    quaternions, checked against its checksum (and those of the files it is stored against);
    a sealed case's models are opened with ``identity`` (refused at once without one)."""
    from reconstructor.case.sealing import reader_seal
    from reconstructor.case.storage import load_model
    from reconstructor.splats import ply

    index = _read(folder)
    seal = reader_seal(folder, index, identity, "its models")
    rows = index.by_name()
    names = at or [e.name for e in index.timestamps if e.status == "done"]
    unknown = [n for n in names if n not in rows]
    if unknown:
        raise CaseFolderError(
            f"{', '.join(unknown)}: not in the case; 'egosurg case info {folder}' lists its names"
        )
    if not names:
        raise CaseFolderError(f"{folder} has no finished timestamp to export yet")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in names:
        g = load_model(folder, rows[name], seal)  # one clear line if not done or damaged
        target = out / f"{name}.{fmt}"
        if fmt == "splat":
            ply.write_splat(target, g)
        else:
            ply.write_ply(target, g, unit_quats=True)
        make_owner_only(target)  # an earlier export's file kept its mode when rewritten
        written.append(target)
    return written


def _read(folder: Path) -> CaseIndex:
    if not (folder / INDEX_NAME).exists():
        raise CaseFolderError(
            f"{folder} is not a case folder (no {INDEX_NAME}); make one with 'egosurg "
            "reconstruct SESSION.h5 --every 1s --out FOLDER'"
        )
    return CaseIndex.read(folder)


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg case", __doc__)
    sub = parser.add_subparsers(dest="verb", required=True)
    p_info = add_subcommand(
        sub, "info", "what is done, pending, failed; sizes; timings; missing or damaged models"
    )
    p_info.add_argument("case", help="a case folder made by 'egosurg reconstruct --every'")
    p_info.add_argument(
        "--verify",
        action="store_true",
        help="read every done model and compare its checksum (default: presence and size only)",
    )
    p_exp = add_subcommand(sub, "export", "timestamps as standard 3DGS PLY (or .splat) files")
    p_exp.add_argument("case")
    p_exp.add_argument("--out", required=True, help="folder to write the files to")
    p_exp.add_argument("--at", action="append", help="a timestamp's name (repeatable; default all)")
    p_exp.add_argument("--format", choices=("ply", "splat"), default="ply")
    add_identity_argument(p_exp)  # a sealed session's case
    args = parser.parse_args(argv)
    if args.verb == "info":
        text, bad = info(Path(args.case), verify=args.verify)
        print(text)
        return 1 if bad else 0
    folder = Path(args.case)
    needed = _read(folder).sealing is not None  # a plaintext case needs no identity
    identity = identity_from_args(args, needed=needed)
    files = export(folder, Path(args.out), args.at, args.format, identity)
    print(f"{args.out}: {len(files)} file(s) exported")
    print(plaintext_notice(f"{len(files)} model(s) as .{args.format}", args.out), file=sys.stderr)
    return 0
