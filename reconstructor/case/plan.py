"""Which timestamps a case holds (``--every``, ``--from``, ``--to``) and what identifies its
settings (the config hash); every bad value is refused here, before any work starts."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xxhash

from protocol.session import SessionReader
from reconstructor.errors import CasePlanError

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:e[-+]?[0-9]+)?)\s*(ms|s)?\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class PlannedTimestamp:
    name: str  # "t<set time>", the model's file stem
    t_s: float  # the set's time, seconds since the session started
    set_index: int


@dataclass(frozen=True)
class SessionTimes:
    started_unix_ns: int
    set_t_s: np.ndarray  # (S,) float64, seconds since the session started

    @property
    def period_s(self) -> float:
        if len(self.set_t_s) < 2:
            return 0.0
        return float(np.median(np.diff(self.set_t_s)))


def parse_duration_s(text: str, option: str = "--every") -> float:
    """``1s``, ``0.5s``, ``500ms`` or a bare number of seconds."""
    m = _DURATION.match(str(text))
    if not m:
        raise CasePlanError(f"{option} {text!r}: write a duration such as 1s, 0.5s or 500ms")
    value = float(m.group(1)) * (1e-3 if (m.group(2) or "s").lower() == "ms" else 1.0)
    if not (math.isfinite(value) and value > 0):
        raise CasePlanError(f"{option} {text!r}: must be a positive duration")
    return value


def session_times(session: Path) -> SessionTimes:
    with SessionReader(session) as reader:
        started = reader.info.started_unix_ns
        set_ns = np.asarray(reader.sets().set_unix_ns, dtype=np.int64)
    if len(set_ns) == 0:
        raise CasePlanError(f"{session} holds no synchronised sets; record a longer session")
    return SessionTimes(started, (set_ns - started) / 1e9)


def timestamp_name(t_s: float) -> str:
    return f"t{t_s:09.3f}"


def plan_timestamps(
    times: SessionTimes, every_s: float, from_s: float | None, to_s: float | None
) -> list[PlannedTimestamp]:
    """One timestamp every ``every_s`` from ``from_s`` to ``to_s`` (default: the session's
    first and last set), each at the nearest set."""
    t = times.set_t_s
    first, last, period = float(t[0]), float(t[-1]), times.period_s
    valid = f"the session runs from {first:.2f}s to {last:.2f}s"
    if period > 0 and every_s < period * 0.999:
        raise CasePlanError(
            f"--every {every_s:g}s is shorter than the session's frame period "
            f"({period:.4f}s, {1 / period:.1f} fps): use --every {period:.4f}s or longer"
        )
    slack = period / 2
    lo = first if from_s is None else from_s
    hi = last if to_s is None else to_s
    for name, value in (("--from", from_s), ("--to", to_s)):
        if value is not None and not (first - slack <= value <= last + slack):
            raise CasePlanError(f"{name} {value:g} is outside the session: {valid}")
    if lo > hi:
        raise CasePlanError(f"--from {lo:g} is after --to {hi:g}; {valid}")
    count = math.floor((hi - lo) / every_s + 1e-6) + 1
    wanted = lo + every_s * np.arange(count)
    out: dict[int, PlannedTimestamp] = {}
    for w in wanted:
        k = int(np.argmin(np.abs(t - w)))
        out.setdefault(k, PlannedTimestamp(timestamp_name(float(t[k])), float(t[k]), k))
    return list(out.values())


def config_hash(config_toml: str, calibration_text: str, warm: str) -> str:
    """xxh3-64 of everything that shapes a model: the resolved config, the calibration and the
    warm-start settings ("" when cold). Two runs with equal hashes make the same models."""
    h = xxhash.xxh3_64()
    for part in (config_toml, calibration_text, warm):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()


def chains(names: list[str], warm_every: int) -> list[int]:
    """The chain of each timestamp: with warm start, runs of ``warm_every`` consecutive
    timestamps (the first of each trained cold), so the models do not depend on how many
    workers share the case; cold, every timestamp is its own chain."""
    if warm_every <= 0:
        return list(range(len(names)))
    return [k // warm_every for k in range(len(names))]
