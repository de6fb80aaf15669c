"""Free-running camera clocks with known truth.

Real ZED X units on two Jetsons are not triggered together: each runs at its own phase, its crystal
is a few ppm off, its timestamps jitter, and now and then a frame is lost. A ``FrameClock`` produces
exactly that, deterministically, so the capture side can be tested against known truth:

- exposure time of frame ``i``: ``phase + i * period * (1 + ppm * 1e-6)`` seconds of sim time;
- stamp (what the ZED SDK reports, the host clock when the frame is complete):
  ``epoch + exposure + readout latency + jitter``, in Unix ns;
- dropped: frame ``i`` never leaves the camera.

Every random draw is keyed by (seed, serial, frame index), so any time range can be asked for in any
order and gives the same frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from protocol.command import CommandArgumentError
from protocol.formats.session_id import SessionId
from sim.errors import SimTimeError

if TYPE_CHECKING:
    from protocol.sealing import Identity

SIM_EPOCH_UNIX_NS = 1_767_225_600_000_000_000  # 2026-01-01T00:00:00Z: sim time 0
SIM_RIG_SOURCE = "egosurg sim rig"  # the case metadata's source of a sim rig's recordings


@dataclass(frozen=True, kw_only=True)
class SessionClock:
    """A recorded session on the sim clock: ``t_sim = sim_offset_s + t_case``."""

    case_metadata: dict[str, str]
    sim_offset_s: float  # the session's start on the sim clock
    set_times_s: np.ndarray  # (N,) case time of each synchronised set; may be empty
    session: SessionId  # what a roles or field file written for it records (its [session])
    # a sealed session read without an identity: its recipients (its metadata is then empty)
    sealed_for: str = ""
    # a sim rig's looping content (``SimRigFiles.sim_metadata``): fps, content fps and the
    # prerendered seconds; None for a session whose pictures are the sim time's own (eval-set)
    content: tuple[float, float, float] | None = None

    def sim_time_s(self, t_case_s: float) -> float:
        """The sim time whose scene the session's pictures show at case time ``t_case_s``: the
        session's start on the sim clock plus ``t_case_s``, and, for a sim rig that loops its
        prerendered content, the content time the cameras showed then."""
        t = self.sim_offset_s + float(t_case_s)
        if self.content is None:
            return t
        fps, content_fps, prerender_s = self.content
        return content_time_s(t, fps=fps, content_fps=content_fps, prerender_s=prerender_s)

    def metadata_needed(self, path: Path, what: str, instead: str = "") -> CommandArgumentError:
        """The one-line error for metadata the session does not give: sealed and read without
        an identity (name the identity option and its recipients), or not written there."""
        from protocol.sealing import IDENTITY_ENV

        other = f" or {instead}" if instead else ""
        if self.sealed_for:
            return CommandArgumentError(
                f"{path} is sealed: its {what} can be read with the identity of one of its "
                f"recipients ({self.sealed_for}): pass --identity FILE (or set "
                f"{IDENTITY_ENV}){other}"
            )
        return CommandArgumentError(f"{path} does not say its {what}: pass {instead}")


def content_time_s(t_sim_s: float, *, fps: float, content_fps: float, prerender_s: float) -> float:
    """The sim time whose scene a simulated camera shows at sim time ``t_sim_s``.

    Mirrors ``capture_agent.sources.sim_source``: prerendered content loops over sim time
    ``[0, N)``; with ``content_fps < fps`` it is quantised to ``1 / content_fps``.
    """
    if prerender_s <= 0:
        return t_sim_s
    if content_fps >= fps:
        loop_s = np.ceil(prerender_s * fps) / fps
        return float(t_sim_s % loop_s)
    count = int(np.ceil(prerender_s * content_fps))
    return float((int(np.floor(t_sim_s * content_fps)) % count) / content_fps)


def read_session_clock(path: Path, identity: Identity | None = None) -> SessionClock:
    """The case metadata and set times of the session file ``path``, on the sim clock (what
    ``egosurg sim roles`` and ``egosurg sim contact`` line their worlds up with). A sealed
    session's metadata is read with ``identity``; without one it is empty and ``sealed_for``
    names the recipients (the set times are never sealed)."""
    from protocol.session import SessionReader  # h5py: only when a session is read

    if not path.is_file():
        raise CommandArgumentError(f"the session {path} does not exist")
    with SessionReader(path, identity=identity) as reader:
        start, name = reader.info.started_unix_ns, reader.info.session_name
        opened = reader.can_open
        sealed_for = "" if opened else ", ".join(r.label() for r in reader.recipients)
        meta = dict(reader.info.case_metadata) if opened else {}
        set_ns = reader.sets().set_unix_ns
    epoch, content = SIM_EPOCH_UNIX_NS, None
    if meta.get("source") == SIM_RIG_SOURCE:  # a live sim rig: its own epoch, looping content
        try:
            epoch = int(meta["sim_epoch_unix_ns"])
            content = (
                float(meta["sim_fps"]),
                float(meta["sim_content_fps"]),
                float(meta["sim_prerender_s"]),
            )
        except (KeyError, ValueError):
            raise CommandArgumentError(
                f"{path} was recorded from a sim rig but does not say its sim clock "
                "(sim_epoch_unix_ns, sim_fps, sim_content_fps, sim_prerender_s): record it "
                "again with this version"
            ) from None
    return SessionClock(
        session=SessionId(name=name, started_unix_ns=int(start)),
        case_metadata=meta,
        sealed_for=sealed_for,
        sim_offset_s=(start - epoch) / 1e9,
        set_times_s=(set_ns - start) / 1e9,
        content=content,
    )


def require_time(t_s: float) -> float:
    t = float(t_s)
    if not np.isfinite(t) or t < 0:
        raise SimTimeError(f"time {t_s} s is invalid: sim time starts at 0 s and must be finite")
    return t


@dataclass(frozen=True, kw_only=True)
class ClockSpec:
    """How a camera free-runs. Zero jitter and drops give an ideal, locked camera."""

    fps: float = 30.0
    free_running: bool = True
    jitter_ns_std: float = 150_000.0
    drop_probability: float = 0.002
    readout_latency_ns: float = 8_000_000.0
    max_abs_ppm: float = 20.0

    def __post_init__(self) -> None:
        if not 0 < self.fps <= 120:
            raise ValueError(f"ClockSpec.fps={self.fps}: the ZED X runs at 15 to 120 fps")
        if not 0 <= self.drop_probability < 0.5:
            raise ValueError(
                f"ClockSpec.drop_probability={self.drop_probability} must be in [0, 0.5)"
            )
        if self.jitter_ns_std < 0:
            raise ValueError(f"ClockSpec.jitter_ns_std={self.jitter_ns_std} must be >= 0")


@dataclass(frozen=True)
class FrameTruth:
    """Arrays over the frames of one camera in a time range."""

    frame_index: np.ndarray  # int64
    exposure_t_s: np.ndarray  # float64, sim time at mid-exposure (what the renderer shows)
    capture_unix_ns: np.ndarray  # int64, what the camera stamps
    dropped: np.ndarray  # bool


@dataclass(frozen=True)
class FrameClock:
    """``epoch_unix_ns`` is the Unix time of sim time 0; agents of one rig share it, so their
    stamps live on one timeline (as PTP-disciplined clocks do)."""

    spec: ClockSpec
    seed: int
    serial: int
    epoch_unix_ns: int = SIM_EPOCH_UNIX_NS

    @property
    def _phase_s(self) -> float:
        if not self.spec.free_running:
            return 0.0
        rng = np.random.default_rng([self.seed, self.serial, 0xC10C])
        return float(rng.uniform(0, 1.0 / self.spec.fps))

    @property
    def period_s(self) -> float:
        ppm = 0.0
        if self.spec.free_running:
            rng = np.random.default_rng([self.seed, self.serial, 0x99])
            ppm = float(rng.uniform(-self.spec.max_abs_ppm, self.spec.max_abs_ppm))
        return (1.0 / self.spec.fps) * (1.0 + ppm * 1e-6)

    def exposure_time(self, frame_index: int) -> float:
        return self._phase_s + frame_index * self.period_s

    def frames(self, t_start_s: float, t_end_s: float) -> FrameTruth:
        """All frames whose exposure falls in ``[t_start_s, t_end_s)``."""
        t0, t1 = require_time(t_start_s), require_time(t_end_s)
        if t1 < t0:
            raise SimTimeError(f"time range {t0}..{t1} s ends before it starts")
        first = max(0, int(np.ceil((t0 - self._phase_s) / self.period_s)))
        last = int(np.ceil((t1 - self._phase_s) / self.period_s))
        idx = np.arange(first, max(first, last), dtype=np.int64)
        exposure = self._phase_s + idx * self.period_s
        keep = (exposure >= t0) & (exposure < t1)
        idx, exposure = idx[keep], exposure[keep]
        jitter = np.empty(len(idx))
        dropped = np.zeros(len(idx), bool)
        for k, i in enumerate(idx):
            u = np.random.default_rng([self.seed, self.serial, int(i)])
            jitter[k] = u.normal(0.0, self.spec.jitter_ns_std) if self.spec.jitter_ns_std else 0.0
            dropped[k] = u.random() < self.spec.drop_probability
        stamp = self.epoch_unix_ns + np.round(
            exposure * 1e9 + self.spec.readout_latency_ns + jitter
        ).astype(np.int64)
        return FrameTruth(idx, exposure, stamp, dropped)
