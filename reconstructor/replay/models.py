"""A case's models by time: which model shows an instant, loaded after its checksum is checked,
and the next ones read in a background thread so that a replay does not wait on the disk.

The model at time t is the case's last done timestamp at or before t (what the rig had seen by
then; never a later one, which would show the future). A case whose timestamps in the asked
span are pending or failed is refused unless the caller allows the gaps. A sealed session's
case is opened with the identity given to the command (docs/case.md, "Sealed cases").
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from protocol.sealing import Identity
from reconstructor.case.index import INDEX_NAME, CaseIndex, Entry
from reconstructor.case.sealing import reader_seal
from reconstructor.case.storage import load_evidence, load_model, load_points
from reconstructor.errors import CaseReplayError
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)


class CaseModels:
    """The done timestamps of a case folder, in time order."""

    def __init__(self, folder: Path | str, identity: Identity | None = None) -> None:
        """``identity``: a recipient's, which opens a sealed session's case (refused here, in
        one line naming the recipients, without one)."""
        self.folder = Path(folder)
        if not (self.folder / INDEX_NAME).is_file():
            raise CaseReplayError(
                f"{self.folder} is not a case folder (no {INDEX_NAME}); make one with "
                "'egosurg reconstruct SESSION.h5 --every 1s --out CASE/'"
            )
        self.index = CaseIndex.read(self.folder)
        self.seal = reader_seal(self.folder, self.index, identity, "its models")
        rows = sorted(self.index.timestamps, key=lambda e: e.t_s)
        self.all_entries = tuple(rows)
        self.entries = tuple(e for e in rows if e.status == "done")
        if not self.entries:
            raise CaseReplayError(
                f"{self.folder} has no finished timestamp yet ({len(rows)} planned); run its "
                "'egosurg reconstruct ... --out' command again to finish it"
            )
        self.times_s = np.array([e.t_s for e in self.entries])

    @property
    def span_s(self) -> tuple[float, float]:
        return float(self.times_s[0]), float(self.times_s[-1])

    @property
    def spacing_s(self) -> float:
        """The case's interval between timestamps (the median of its plan, done or not: a gap
        is what makes a model old); 0 for a case of one timestamp."""
        t = np.array([e.t_s for e in self.all_entries])
        return float(np.median(np.diff(t))) if len(t) > 1 else 0.0

    def require_span(self, t0_s: float, t1_s: float, allow_gaps: bool = False) -> None:
        """Refuse a span outside the case, or one over unfinished timestamps."""
        c0, c1 = self.span_s
        if t0_s < c0 - 1e-6:
            raise CaseReplayError(
                f"time {t0_s:.3f} s is before the case's first model ({c0:.3f} s); the case "
                f"spans {c0:.3f} s to {c1:.3f} s"
            )
        gaps = [e.name for e in self.all_entries if e.status != "done" and t0_s <= e.t_s <= t1_s]
        if gaps and not allow_gaps:
            raise CaseReplayError(
                f"{self.folder} misses timestamps {', '.join(gaps[:5])}"
                f"{' ...' if len(gaps) > 5 else ''} in {t0_s:.3f}-{t1_s:.3f} s (pending or "
                "failed): finish the case, or pass --allow-gaps to show the model before each"
            )

    def entry_at(self, t_s: float) -> Entry:
        k = int(np.searchsorted(self.times_s, t_s + 1e-6, side="right")) - 1
        if k < 0:
            raise CaseReplayError(
                f"time {t_s:.3f} s is before the case's first model ({self.span_s[0]:.3f} s)"
            )
        return self.entries[k]

    def load(self, entry: Entry) -> Gaussians:
        """The entry's model (a full PLY or compact storage), after checking it is the file
        the index names; one line naming the file and what to do otherwise."""
        return load_model(self.folder, entry, self.seal)

    def load_points(self, entry: Entry) -> np.ndarray | None:
        """The fused stereo points stored with the entry's model (``storage.load_points``)."""
        return load_points(self.folder, entry, self.seal)

    def load_evidence(self, entry: Entry) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The observed points stored with the entry's model and each one's metres of depth
        per pixel of disparity (None in cases made before they were kept):
        ``storage.load_evidence``."""
        return load_evidence(self.folder, entry, self.seal)


class ModelSource:
    """Models in the order a replay asks for them; with ``preload``, a background thread reads
    the next ``ahead`` distinct models while the current one renders.

    ``waited_s`` is the time the caller spent blocked on loading: the I/O a replay could not
    hide."""

    def __init__(
        self, models: CaseModels, order: list[Entry], *, preload: bool = True, ahead: int = 2
    ) -> None:
        self.models = models
        self.preload = preload
        self.ahead = max(1, ahead)
        # the distinct models in replay order: what to read next
        self._plan: list[Entry] = []
        for e in order:
            if not self._plan or self._plan[-1].name != e.name:
                self._plan.append(e)
        self._pos = 0
        self._futures: dict[str, Future[Gaussians]] = {}
        self._current: tuple[str, Gaussians] | None = None
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="replay-preload") if preload else None
        self._lock = threading.Lock()
        self.waited_s = 0.0
        self.loads = 0

    def get(self, entry: Entry) -> Gaussians:
        if self._current is not None and self._current[0] == entry.name:
            return self._current[1]
        t0 = time.perf_counter()
        if self._pool is None:
            g = self.models.load(entry)
        else:
            with self._lock:
                fut = self._futures.pop(entry.name, None)
                if fut is None:
                    fut = self._pool.submit(self.models.load, entry)
            g = fut.result()  # re-raises a load's CaseReplayError here, in the caller
        self.waited_s += time.perf_counter() - t0
        self.loads += 1
        self._current = (entry.name, g)
        self._advance(entry)
        return g

    def _advance(self, entry: Entry) -> None:
        names = [e.name for e in self._plan]
        if entry.name in names[self._pos :]:
            self._pos = names.index(entry.name, self._pos) + 1
        if self._pool is None:
            return
        with self._lock:
            wanted = self._plan[self._pos : self._pos + self.ahead]
            keep = {e.name for e in wanted}
            for name in [n for n in self._futures if n not in keep]:
                self._futures.pop(name).cancel()  # passed by: free its memory
            for e in wanted:
                if e.name not in self._futures:
                    self._futures[e.name] = self._pool.submit(self.models.load, e)

    def close(self) -> None:
        if self._pool is not None:
            for fut in self._futures.values():
                fut.cancel()
            self._pool.shutdown(wait=True)

    def __enter__(self) -> ModelSource:
        if self._pool is not None:
            with self._lock:
                for e in self._plan[: self.ahead]:
                    if e.name not in self._futures:
                        self._futures[e.name] = self._pool.submit(self.models.load, e)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
