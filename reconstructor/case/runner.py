"""Run a case: open (or resume) its folder, then reconstruct every timestamp not yet done, here,
in a pool of processes, or as Ray tasks, updating the index after each one.

The runner is the index's only writer. It holds ``.lock`` (flock) for the whole run, so a second
run on the same folder is refused instead of racing. On resume, done entries whose model is
missing or fails its checksum go back to pending, and leftovers of a killed run (``.work/``,
``*.partial``) are removed.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path

from tqdm import tqdm

from protocol.durable import atomic_write_bytes
from reconstructor.case.index import INDEX_NAME, CaseIndex, Entry
from reconstructor.case.plan import PlannedTimestamp, chains
from reconstructor.case.work import ChainJob, StepJob, StepResult, limit_threads, run_chain
from reconstructor.errors import CaseFolderError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CaseRequest:
    case_dir: Path
    session: Path
    session_started_unix_ns: int
    calibration_text: str
    config_toml: str
    warm_toml: str  # "" without warm start
    warm: dict  # WarmStartConfig fields ({} without warm start)
    config_hash: str
    planned: tuple[PlannedTimestamp, ...]
    workers: int = 1
    ray: str = ""  # "" local; "auto" or an address
    gpus_per_task: int = 0  # 1 when the config trains on CUDA: each Ray task declares a GPU
    force: bool = False
    depth_cache: str = ""  # a folder keeping each timestamp's depth stage ("": none)
    identity: str = ""  # the identity file that opens a sealed session ("": none)
    sealing: dict | None = None  # a sealed session's CaseIndex.sealing (None: plaintext)


@contextmanager
def case_lock(folder: Path) -> Iterator[None]:
    with (folder / ".lock").open("a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CaseFolderError(
                f"another 'egosurg reconstruct' is writing {folder}; wait for it to finish or "
                "stop it (its finished timestamps are kept)"
            ) from None
        yield


def prepare_folder(folder: Path) -> None:
    """Refuse a folder that is a file, another program's, or unwritable."""
    if folder.exists() and not folder.is_dir():
        raise CaseFolderError(f"--out {folder} is a file; give a folder for the case")
    if folder.is_dir() and any(folder.iterdir()) and not (folder / INDEX_NAME).exists():
        raise CaseFolderError(
            f"--out {folder} holds other files and no {INDEX_NAME}: it is not a case folder; "
            "give a new or empty folder"
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-probe.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise CaseFolderError(
            f"cannot write to --out {folder} ({exc.strerror}); choose a folder you can write"
        ) from None


def open_index(req: CaseRequest) -> CaseIndex:
    """The folder's index, checked against this run and merged with its timestamps."""
    folder = req.case_dir
    if (folder / INDEX_NAME).exists():
        index = CaseIndex.read(folder)
        if index.session_started_unix_ns != req.session_started_unix_ns:
            raise CaseFolderError(
                f"{folder} is the case of another session ({index.session}); give a new --out "
                "folder for this one"
            )
        if index.config_hash != req.config_hash:
            if not req.force:
                raise CaseFolderError(
                    f"{folder} was reconstructed with other settings (config hash "
                    f"{index.config_hash}, now {req.config_hash}); rerun with the same options, "
                    "use a new --out folder, or add --force to redo every timestamp"
                )
            log.warning("--force: settings changed, every timestamp of %s is redone", folder)
            redo = tuple(
                replace(e, status="pending", model="", xxh3_64="") for e in index.timestamps
            )
            index = replace(index, timestamps=redo, config_hash=req.config_hash)
    else:
        index = CaseIndex(
            session=str(req.session.resolve()),
            session_started_unix_ns=req.session_started_unix_ns,
            config_hash=req.config_hash,
            warm_start=bool(req.warm_toml),
            created_unix_ns=time.time_ns(),
        )
    # a case made before models were sealed takes its session's seal; its plaintext models
    # fail entry_is_intact below and are redone sealed
    index = replace(index, warm_start=bool(req.warm_toml), sealing=req.sealing)
    from reconstructor.case.sealing import identity_file_seal
    from reconstructor.case.storage import SEALED_SUFFIX, entry_is_intact  # torch: not before

    seal = identity_file_seal(folder, index, req.identity)

    known = index.by_name()
    names = [p.name for p in req.planned]
    chain_of = dict(zip(names, chains(names, req.warm.get("keyframe_every", 0)), strict=True))
    rows: list[Entry] = list(index.timestamps)
    for p in req.planned:
        if p.name not in known:
            rows.append(Entry(name=p.name, t_s=p.t_s, set_index=p.set_index))
    rows.sort(key=lambda e: e.t_s)
    out = []
    for e in rows:
        if e.name in chain_of:
            e = replace(e, chain=chain_of[e.name])
        # a compact model is checked with the files it is stored against: one whose parent is
        # damaged (and so redone) is redone too
        if e.status == "done" and not entry_is_intact(folder, e, seal):
            log.warning("%s: its model is missing or damaged; it is redone", e.name)
            if seal is not None and e.model and not e.model.endswith(SEALED_SUFFIX):
                (folder / e.model).unlink(missing_ok=True)  # plaintext in a sealed case
            e = replace(e, status="pending", model="", xxh3_64="", bytes=0)
        out.append(e)
    return replace(index, timestamps=tuple(out))


def clean_leftovers(folder: Path) -> None:
    """What a killed run left: its work folders and partial files."""
    shutil.rmtree(folder / ".work", ignore_errors=True)
    for sub in (folder, folder / "models"):
        if sub.is_dir():
            for p in sub.glob(".*.partial"):
                p.unlink(missing_ok=True)


def run_case(req: CaseRequest, step_progress: Callable | None = None) -> CaseIndex:
    prepare_folder(req.case_dir)
    with case_lock(req.case_dir):
        index = open_index(req)
        clean_leftovers(req.case_dir)
        (req.case_dir / "config.toml").write_text(req.config_toml)
        if req.warm_toml:
            (req.case_dir / "config_warm.toml").write_text(req.warm_toml)
        atomic_write_bytes(req.case_dir / "calibration.toml", req.calibration_text.encode())
        index.write(req.case_dir)
        return _run(req, index, step_progress)


def _run(req: CaseRequest, index: CaseIndex, step_progress: Callable | None) -> CaseIndex:
    wanted = {p.name for p in req.planned}
    queues = _chains(index, wanted, warm=bool(req.warm_toml))
    todo = sum(len(q) for q in queues)
    state = {"index": index}
    bar = tqdm(total=len(wanted), initial=len(wanted) - todo, unit="timestamp", desc="case")

    def record(result: StepResult) -> None:
        entry = state["index"].by_name()[result.name]
        if result.ok:
            entry = replace(
                entry, status="done", model=result.model, xxh3_64=result.xxh3_64,
                bytes=result.bytes, seconds=result.seconds, gaussians=result.gaussians,
                config_hash=req.config_hash, warm_from=result.warm_from, error="",
            )  # fmt: skip
        else:
            entry = replace(entry, status="failed", error=result.error)
            tqdm.write(f"{result.name}: failed: {result.error}")
        state["index"] = state["index"].with_entry(entry)
        state["index"].write(req.case_dir)
        bar.update(1)

    try:
        if req.ray:
            from reconstructor.case.ray_backend import run_on_ray

            threads = threads_per_worker(req.workers)
            run_on_ray(
                req.ray, threads, queues, lambda q, t: _job(req, q, t), record, req.gpus_per_task
            )
        elif req.workers <= 1:
            for queue in queues:
                run_chain(_job(req, queue), progress=step_progress, on_done=record)
        else:
            _run_pool(req, queues, record)
    finally:
        bar.close()
    return state["index"]


def _chains(index: CaseIndex, wanted: set[str], warm: bool) -> list[list[StepJob]]:
    """The pending steps, by chain; a warm step starts from the entry before it in its chain."""
    by_chain: dict[int, list[Entry]] = {}
    for e in index.timestamps:
        if e.name in wanted:
            by_chain.setdefault(e.chain, []).append(e)
    queues = []
    for rows in by_chain.values():
        queue, previous = [], ""
        for e in rows:
            if e.status != "done":
                queue.append(StepJob(name=e.name, set_index=e.set_index, warm_from=previous))
            previous = e.name if warm else ""
        if queue:
            queues.append(queue)
    return queues


def _job(req: CaseRequest, steps: list[StepJob], threads: int = 0) -> ChainJob:
    return ChainJob(
        case_dir=str(req.case_dir),
        session=str(req.session),
        calibration=str(req.case_dir / "calibration.toml"),
        config_toml=req.config_toml,
        warm_toml=req.warm_toml,
        warm=dict(req.warm),
        steps=tuple(steps),
        threads=threads,
        depth_cache=req.depth_cache,
        identity=req.identity,
    )


def threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _run_pool(req: CaseRequest, queues: list[list[StepJob]], record: Callable) -> None:
    """One step per task; a chain's next step is submitted when the one before it is done, so
    the index is updated after every timestamp and warm steps still run in order."""
    threads = threads_per_worker(req.workers)
    ctx = get_context("spawn")  # fork would copy torch's and numba's thread pools
    with ProcessPoolExecutor(req.workers, mp_context=ctx, initializer=limit_threads,
                             initargs=(threads,)) as pool:  # fmt: skip
        pending: dict[Future, list[StepJob]] = {}

        def submit(queue: list[StepJob]) -> None:
            if queue:
                pending[pool.submit(run_chain, _job(req, queue[:1], threads))] = queue[1:]

        for queue in queues:
            submit(queue)
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                rest = pending.pop(fut)
                (result,) = fut.result()
                record(result)
                if rest and not result.ok:  # its follower cannot start from it
                    rest = [replace(rest[0], warm_from=""), *rest[1:]]
                submit(rest)
