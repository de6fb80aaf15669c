"""Fuzzing at scale: the properties of tests/capture_agent/test_fuzz.py over 100k+ cases per
decoder and per control socket, and over mutated session files, from a seeded mutator
(tests/fuzzing.py).

    .venv/bin/python bench/bench_fuzz.py --cases 100000 [--files 1000] [--seed 0]

Targets: the frame/status decoder (``decode_published``), ``AgentStatus``, ``ControlRequest``,
``ControlReply``; a real recorder's and a real agent's control sockets (in-process daemons,
their own threads, plaintext loopback: every request must get exactly one reply and the daemon
must answer ``status`` after it); the session reader on damaged copies of a small real session
(in a child process, a hang is a read over ``--read-limit-s``). Prints a Markdown table (target,
cases, accepted, rejections counted, crashes, hangs, seconds), then the first few failures of
each target with the input that caused them (the seed and case number reproduce it).
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests import fuzzing
from tests.fuzzing import Hang, RandomChooser
from tests.helpers import loopback_rig_config, loopback_sim_node

MAX_SHOWN = 3  # failures printed per target


class Tally:
    def __init__(self, target: str) -> None:
        self.target = target
        self.counts: collections.Counter[str] = collections.Counter()
        self.failures: list[str] = []
        self.seconds = 0.0
        self.daemon_counted: int | None = None  # not-ok answers the daemon's own counts show

    def add(self, outcome: str, detail: str = "") -> None:
        self.counts[outcome] += 1
        if outcome in ("crash", "hang") and len(self.failures) < MAX_SHOWN:
            self.failures.append(detail)

    def row(self) -> str:
        c = self.counts
        cases = sum(c.values())
        rejected = str(c["rejected"])
        if self.daemon_counted is not None:
            rejected += f" (daemon counted {self.daemon_counted})"
        return (
            f"| {self.target} | {cases} | {c['accepted']} | {rejected} | {c['crash']} | "
            f"{c['hang']} | {self.seconds:.1f} |"
        )


def _run(tally: Tally, cases: int, seed: int, one: Callable[[RandomChooser], tuple[str, str]]):
    t0 = time.perf_counter()
    for k in range(cases):
        c = RandomChooser(seed * 1_000_003 + k)  # each case reproducible on its own
        try:
            outcome, detail = one(c)
        except Hang as exc:
            outcome, detail = "hang", f"case {k}: {exc}"
        except Exception as exc:
            where = traceback.extract_tb(exc.__traceback__)[-1]
            outcome = "crash"
            detail = (
                f"case {k}: {type(exc).__name__}: {str(exc)[:200]} ({where.name}:{where.lineno})"
            )
        tally.add(outcome, detail)
    tally.seconds = time.perf_counter() - t0
    return tally


def _decoders(cases: int, seed: int) -> list[Tally]:
    def frames(c):
        parts = fuzzing.frame_case(c)
        return fuzzing.decode_frame_or_status(parts), repr([p[:80] for p in parts])

    def one_kind(kind: str, make):
        def run(c):
            data = make(c)
            return fuzzing.decode_control(data, kind), repr(data[:160])

        return run

    return [
        _run(Tally("decode_published (frame + status)"), cases, seed, frames),
        _run(Tally("AgentStatus.from_parts"), cases, seed, one_kind("status", fuzzing.status_case)),
        _run(
            Tally("ControlRequest.from_bytes"),
            cases,
            seed,
            one_kind("request", lambda c: fuzzing.control_case(c)[0]),
        ),
        _run(Tally("ControlReply.from_bytes"), cases, seed, one_kind("reply", fuzzing.reply_case)),
    ]


def _socket(name: str, endpoint: str, cases: int, seed: int, daemon) -> Tally:
    """``daemon``: the recorder or agent, for its thread check and its ``control.counts()``."""
    probes = [fuzzing.ControlProbe(endpoint)]  # a fresh one after a hang: a late reply waits
    before = daemon.control.counts()

    def alive() -> bool:
        threads = getattr(daemon, "_threads", None) or [daemon._thread]
        return all(t is not None and t.is_alive() for t in threads)

    def one(c):
        parts = fuzzing.control_case(c)
        if not alive():
            raise AssertionError("the daemon's thread is gone")
        try:
            reply = probes[-1].send(parts)
        except Hang:
            probes[-1].close()
            probes.append(fuzzing.ControlProbe(endpoint))
            raise
        return ("accepted" if reply.ok else "rejected"), repr([p[:80] for p in parts])

    try:
        tally = _run(Tally(name), cases, seed, one)
    finally:
        probes[-1].close()
    after = daemon.control.counts()
    # every request that was not answered ok shows in the daemon's counts (status reports them)
    tally.daemon_counted = (after["requests"] - before["requests"]) - (
        after["answered_ok"] - before["answered_ok"]
    )
    return tally


def _daemons(cases: int, seed: int, tmp: Path) -> list[Tally]:
    from capture_agent.agent.agent import Agent
    from capture_agent.recorder.recorder import Recorder

    recorder = Recorder(loopback_rig_config(tmp / "sessions", rig_name="fuzz"))
    agent = Agent(loopback_sim_node("orin-f", fps=5.0, seed=2, where="bench node.toml"))
    recorder.start()
    agent.start()
    try:
        return [
            _socket(
                "recorder control socket",
                recorder.config.control_bind,
                cases,
                seed,
                recorder,
            ),
            _socket(
                "agent control socket",
                agent.config.control_bind,
                cases,
                seed,
                agent,
            ),
        ]
    finally:
        agent.stop()
        recorder.stop()


def _sessions(files: int, seed: int, tmp: Path, limit_s: float) -> Tally:
    original_path = fuzzing.write_small_session(tmp / "original.h5")
    original = original_path.read_bytes()
    live = fuzzing.live_ranges(original)
    worker = fuzzing.ReaderWorker()
    target = tmp / "damaged.h5"
    keep = tmp / "failures"
    keep.mkdir()

    def one(c):
        damaged, what = fuzzing.damage(c, original, live)
        target.unlink(missing_ok=True)
        target.write_bytes(damaged)
        result = worker.read(target, limit_s)
        outcome = result["outcome"]
        if outcome in ("crash", "hang"):
            kept = keep / f"case-{len(list(keep.iterdir()))}.h5"
            kept.write_bytes(damaged)
            what += f" (kept as {kept})"
        return outcome, f"{what}: {result.get('error', '')}"

    try:
        return _run(
            Tally(f"SessionReader, damaged {len(original) // 1000} kB file"), files, seed, one
        )
    finally:
        worker.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cases", type=int, default=100_000, help="per decoder and socket")
    parser.add_argument("--files", type=int, default=1000, help="damaged session files")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--read-limit-s", type=float, default=fuzzing.READ_LIMIT_S)
    parser.add_argument("--keep", help="folder to keep damaged files that crash or hang")
    args = parser.parse_args()

    import logging

    logging.disable(logging.WARNING)  # every rejection is logged by design; the table counts
    with tempfile.TemporaryDirectory(prefix="bench-fuzz-") as tmp_name:
        tmp = Path(args.keep) if args.keep else Path(tmp_name)
        tmp.mkdir(parents=True, exist_ok=True)
        tallies = _decoders(args.cases, args.seed)
        tallies += _daemons(args.cases, args.seed, tmp)
        tallies.append(_sessions(args.files, args.seed, tmp, args.read_limit_s))
        limits = (
            f"{fuzzing.DECODE_LIMIT_S:g} s decode / {fuzzing.REPLY_LIMIT_S:g} s reply / "
            f"{args.read_limit_s:g} s read"
        )
        print(
            f"\nbench_fuzz: seed {args.seed}, {args.cases} cases per decoder and socket, "
            f"{args.files} damaged files (a hang: no answer in {limits})\n"
        )
        print("| target | cases | accepted | rejected (counted) | crashes | hangs | seconds |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for t in tallies:
            print(t.row())
        for t in tallies:
            for detail in t.failures:
                print(f"\n{t.target}: {detail}")
        if any(t.counts["crash"] or t.counts["hang"] for t in tallies):
            sys.exit(1)


if __name__ == "__main__":
    main()
