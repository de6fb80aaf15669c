"""The case's timestamps as Ray tasks (``egosurg reconstruct ... --ray auto|ADDRESS``).

Each timestamp is one task that declares its resources: ``num_cpus`` (the threads it may use)
and, when the config trains on CUDA (``--device cuda``), ``num_gpus=1``: Ray then runs a
timestamp only where a GPU is free, one per GPU. Workers read the frames from the session file and
write the models into the case folder, so both must be on storage every node mounts at the same
path (NFS, a cluster file system). A task takes this machine's cores // ``--workers`` CPUs, the
threads a local pool worker gets, so both make the same models. The runner on the driver
writes the index. A chain's warm steps are submitted one after another, as in the local pool.

``auto`` connects to the cluster ``RAY_ADDRESS`` or ``ray start`` on this machine names, and
otherwise starts a local instance; an address (``HOST:PORT`` or ``ray://HOST:PORT``) is probed
with a plain TCP connection first, so one that does not answer fails in seconds with one line
instead of Ray's long retry loop.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from reconstructor.errors import RayUnavailableError

if TYPE_CHECKING:
    from reconstructor.case.work import ChainJob, StepJob

log = logging.getLogger(__name__)
PROBE_TIMEOUT_S = 5.0


def _probe(address: str) -> None:
    target = address.removeprefix("ray://")
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        raise RayUnavailableError(
            f"--ray {address!r}: give 'auto' or the head node as HOST:PORT (e.g. 10.0.0.5:6379)"
        )
    try:
        with socket.create_connection((host, int(port)), timeout=PROBE_TIMEOUT_S):
            pass
    except OSError as exc:
        raise RayUnavailableError(
            f"the Ray cluster at {address} does not answer ({exc.strerror or exc}); start it "
            "with 'ray start --head' there, check the address, or drop --ray to run here"
        ) from None


def connect(address: str) -> Any:
    try:
        import ray
    except ImportError:
        raise RayUnavailableError(
            "--ray needs Ray: pip install 'egosurg[cluster]' (or drop --ray to run here)"
        ) from None
    if ray.is_initialized():
        return ray
    if address != "auto":
        _probe(address)
    try:
        ray.init(address=None if address == "auto" else address, log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise RayUnavailableError(f"cannot join the Ray cluster at {address}: {exc}") from None
    return ray


def run_on_ray(
    address: str,
    threads: int,
    queues: list[list[StepJob]],
    make_job: Callable[[list[StepJob], int], ChainJob],
    record: Callable[[Any], None],
    gpus_per_task: int = 0,
) -> None:
    """Run the queues' steps as tasks of ``threads`` CPUs (and ``gpus_per_task`` GPUs) each, a
    chain's steps in order."""
    from reconstructor.case.work import run_chain

    ray = connect(address)
    cpus = int(ray.cluster_resources().get("CPU", os.cpu_count() or 1))
    # as many threads as a local pool worker would get, so both make the same models
    per_task = min(threads, cpus)
    options: dict[str, Any] = {"num_cpus": per_task}
    if gpus_per_task:  # Ray then places each task on a node with a free GPU, one at a time
        options["num_gpus"] = gpus_per_task
    task = ray.remote(run_chain).options(**options)
    log.info("Ray: %d CPUs in the cluster, %d per timestamp", cpus, per_task)
    pending: dict[Any, list[StepJob]] = {}

    def submit(queue: list[StepJob]) -> None:
        if queue:
            pending[task.remote(make_job(queue[:1], per_task))] = queue[1:]

    for queue in queues:
        submit(queue)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            rest = pending.pop(ref)
            (result,) = ray.get(ref)
            record(result)
            if rest and not result.ok:
                rest = [replace(rest[0], warm_from=""), *rest[1:]]
            submit(rest)
