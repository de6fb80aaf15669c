"""What each finished job of an evaluation leaves on disk, so that a stopped run resumes.

A full-scale evaluation is hours of work on a CPU (81 reconstructions overnight);
a power cut, a killed terminal or a machine that must be given back would otherwise lose all
of it. After each job (one timestamp, every method) the runner writes, in ``OUT/jobs/``:

- ``<job>.json``: its image scores, the seconds of each reconstruction, the refiner's
  description and the settings that made it (the record: written last, atomically, so a job
  whose record exists is complete);
- ``<job>.frames.npz``: the renders a temporal sequence keeps for its stability scores
  (uint8, one array per sequence x camera x method of this frame), when the job is a frame;
- ``<job>.warm.npz``: the warm-start row's model of this frame (the next frame starts from it).

``egosurg evaluate ... --resume`` then loads every recorded job instead of running it, and
runs the rest; the tables and the report are made from all of them. A record made with other
settings (another step count, methods, evaluation set...) is refused by name rather than
mixed in; which scenes a run chose is not compared, so a run split by ``--scenes`` over
processes or machines merges by copying their ``jobs/`` folders into one ``--out`` and
resuming there. A record made by other code (a digest of the reconstructor's and protocol's Python
sources, which compute every number) is loaded with a warning naming how many: resuming
after a fix is legitimate, but the reader of the tables should know they mix code versions.
"""

from __future__ import annotations

import functools
import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
import xxhash

from protocol import __version__
from protocol.command import CommandArgumentError
from reconstructor.evaluation.methods import EvalSettings
from reconstructor.evaluation.plan import Job
from reconstructor.evaluation.tables import ImageScore
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)

RECORD_FORMAT = 1
JOBS_DIR = "jobs"
# settings that do not change a job's numbers: where the set was read from, how it was named,
# and which of its scenes the run chose (a job is one scene's timestamp, named by its file): a
# run split by --scenes over processes or machines is merged by copying their jobs/ together
_NOT_COMPARED = ("eval_set", "eval_set_description", "scenes", "phases")

FrameKey = tuple[str, str, str, int]  # (sequence, camera, method, frame)


@dataclass
class JobRecord:
    """Everything one finished job added to the run's results."""

    image_scores: list[ImageScore] = field(default_factory=list)
    recon_seconds: dict[str, list[float]] = field(default_factory=dict)
    refiner: str = ""
    seconds: float = 0.0  # the job's wall time
    frames: dict[FrameKey, np.ndarray] = field(default_factory=dict)
    sequence_phase: dict[str, str] = field(default_factory=dict)
    warm: tuple[str, int, Gaussians] | None = None  # (sequence, frame, model)
    # the libraries that made its depth stage(s) (DepthStage.made_by); None: a record written
    # before they were kept
    depth_made_by: list[dict[str, str]] | None = field(default_factory=list)


def job_name(job: Job) -> str:
    """A file stem for a job, e.g. ``intraoperative-later_set2_all`` (scene names are free
    text in the set's manifest)."""
    raw = f"{job.scene.name}_set{job.scene.set_index}_{job.train_views}"
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in raw)


@functools.cache
def code_digest() -> str:
    """xxh3-64 over the Python sources of ``reconstructor/`` and ``protocol/`` (paths and
    contents, in order): the code that computes an evaluation's numbers."""
    root = Path(__file__).resolve().parents[2]
    h = xxhash.xxh3_64()
    for package in ("reconstructor", "protocol"):
        for path in sorted((root / package).rglob("*.py")):
            h.update(str(path.relative_to(root)).encode() + b"\0")
            h.update(path.read_bytes())
    return h.hexdigest()


def _comparable(settings: EvalSettings) -> dict[str, Any]:
    d = settings.as_dict()
    return {k: v for k, v in d.items() if k not in _NOT_COMPARED}


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value))  # tuples -> lists, as a record reads back


class JobRecords:
    """The ``OUT/jobs/`` folder of one run."""

    def __init__(self, out_dir: Path, settings: EvalSettings) -> None:
        self.folder = Path(out_dir) / JOBS_DIR
        self.settings = settings

    def finished(self) -> list[Path]:
        return sorted(self.folder.glob("*.json")) if self.folder.is_dir() else []

    def check_start(self, resume: bool) -> int:
        """Before any work: the number of recorded jobs a resumed run will load. Without
        ``resume`` an earlier run's records are never overwritten; with it, a record made with
        other settings is refused, naming them."""
        done = self.finished()
        if not done:
            return 0
        if not resume:
            raise CommandArgumentError(
                f"--out {self.folder.parent} holds {len(done)} finished job(s) of an earlier "
                "run: add --resume to continue it, or give another --out"
            )
        mine = _jsonable(_comparable(self.settings))
        other_code = 0
        for path in done:
            data = self._read(path)
            other_code += data.get("code", code_digest()) != code_digest()
            theirs = data.get("settings")
            if not isinstance(theirs, dict):
                raise CommandArgumentError(
                    f"--resume: {path} names no settings; delete it to run that job again"
                )
            differ = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
            if differ:
                shown = ", ".join(f"{k} {theirs.get(k)!r} (now {mine.get(k)!r})" for k in differ)
                raise CommandArgumentError(
                    f"--resume: {path} was made with other settings: {shown}; run with the "
                    "same options, or give another --out"
                )
        if other_code:
            log.warning(
                "--resume: %d of %d recorded job(s) were made by other code (the reconstructor's "
                "or protocol's sources have changed since): the tables will mix code versions; "
                "for one version, run again into another --out",
                other_code,
                len(done),
            )
        return len(done)

    def _record_path(self, job: Job) -> Path:
        return self.folder / f"{job_name(job)}.json"

    def missing(self, jobs: list[Job]) -> int:
        """How many of ``jobs`` have no record yet (the work a resumed run has left)."""
        return sum(not self._record_path(j).exists() for j in jobs)

    def _read(self, path: Path) -> dict[str, Any]:
        try:
            data = json.loads(path.read_text())
            if not isinstance(data, dict):
                raise ValueError("not a JSON object")
            if data.get("format") != RECORD_FORMAT:
                raise ValueError(f"format {data.get('format')!r}, expected {RECORD_FORMAT}")
            return data
        except (OSError, ValueError) as exc:
            raise CommandArgumentError(
                f"--resume: {path} cannot be read ({exc}); delete it to run that job again"
            ) from exc

    def load(self, job: Job) -> JobRecord | None:
        """The job's record, or None if it has not finished."""
        path = self._record_path(job)
        if not path.exists():
            return None
        data = self._read(path)
        try:
            record = JobRecord(
                image_scores=[ImageScore(**s) for s in data["image_scores"]],
                recon_seconds={k: list(v) for k, v in data["recon_seconds"].items()},
                refiner=str(data["refiner"]),
                seconds=float(data["seconds"]),
                sequence_phase=dict(data["sequence_phase"]),
                depth_made_by=_made_by(data.get("depth_made_by")),
            )
            if data["frames"]:
                with np.load(self.folder / f"{job_name(job)}.frames.npz") as npz:
                    for i, (seq, cam, method, k) in enumerate(data["frames"]):
                        record.frames[(seq, cam, method, int(k))] = npz[f"f{i}"]
            if data["warm"] is not None:
                seq, k = data["warm"]
                with np.load(self.folder / f"{job_name(job)}.warm.npz") as npz:
                    model = Gaussians(**{n: torch.from_numpy(npz[n]) for n in npz.files})
                record.warm = (seq, int(k), model)
        except (OSError, KeyError, ValueError, TypeError, AttributeError) as exc:
            raise CommandArgumentError(
                f"--resume: {path} or its arrays cannot be read ({exc!r}); delete {path} to run "
                "that job again"
            ) from exc
        return record

    def save(self, job: Job, record: JobRecord) -> None:
        """Write the job's arrays, then its record (atomically: a record names a whole job)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        stem = self.folder / job_name(job)
        keys = list(record.frames)  # in the order the run made them (the tables keep it)
        if keys:
            arrays = {f"f{i}": record.frames[k] for i, k in enumerate(keys)}
            _atomic_npz(Path(f"{stem}.frames.npz"), arrays)
        if record.warm is not None:
            model = record.warm[2]
            arrays = {n: t.detach().cpu().numpy() for n, t in model.parameters_dict().items()}
            _atomic_npz(Path(f"{stem}.warm.npz"), arrays)
        data = {
            "format": RECORD_FORMAT,
            "egosurg": __version__,
            "code": code_digest(),
            "job": job_name(job),
            "settings": _comparable(self.settings),
            "image_scores": [asdict(s) for s in record.image_scores],
            "recon_seconds": record.recon_seconds,
            "refiner": record.refiner,
            "seconds": record.seconds,
            "sequence_phase": record.sequence_phase,
            "frames": [list(k) for k in keys],
            "warm": None if record.warm is None else [record.warm[0], record.warm[1]],
            "depth_made_by": record.depth_made_by,
        }
        tmp = Path(f"{stem}.json.tmp")
        tmp.write_text(json.dumps(data, indent=1) + "\n")
        os.replace(tmp, f"{stem}.json")


def _made_by(value: Any) -> list[dict[str, str]] | None:
    """A record's ``depth_made_by``: a list of {library: version}, or None (not kept then)."""
    if value is None:
        return None
    if not isinstance(value, list) or not all(
        isinstance(m, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in m.items())
        for m in value
    ):
        raise ValueError(f"depth_made_by {value!r} is not a list of {{library: version}}")
    return value


def _atomic_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        # numpy's stubs (2.1 on) let a ** key fill savez's allow_pickle flag; no key here is
        # that name, and numpy 1.26 (supported) has no flag to pass instead: the arrays as Any
        np.savez(fh, **cast(dict[str, Any], arrays))
    os.replace(tmp, path)
