"""Group the frames of N free-running cameras into synchronised sets, online.

Contract (docs/session.md, "Synchronised sets"): frames are grouped by capture timestamp, never by
arrival; a set's tolerance is half a frame period; a camera with no frame in a set is an explicit
missing marker (``None`` here, ``MISSING = -1`` in the session table), never a silent shift; every
set records its spread. As in ROS message_filters' ApproximateTime, each frame is used at most once.

The cameras are not triggered together: each free-runs with its own phase (anything in [0, P)), a
rate a few ppm off the nominal one, and jittered stamps. The synchroniser therefore keeps its own
reference timeline that follows the cameras' common clock.

Algorithm, step by step
-----------------------
Let ``P = 1e9 / fps`` ns (the rig's nominal frame period) and ``H = P / 2`` (the tolerance).
Internally times are float ns offsets from an integer origin (the earliest first frame), so float
rounding stays far below 1 ns over days of recording.

1. **Anchor.** When every camera has delivered its first frame (or has been silent for
   ``max_wait_ns``, or was removed), take each camera's first stamp, its phase ``(stamp - origin)
   mod P`` on the circle [0, P), and the largest gap between neighbouring phases (wrap-around
   included). The reference ``t_0`` is the middle of the arc opposite that gap, taken within ``H``
   of the origin: the window edges then sit in the middle of the largest gap, as far from every
   camera as the phases allow (at least ``P / (2N)`` for N cameras).
2. **Windows.** Window k is ``[t_k - H, t_k + H]``, both ends included. Per camera, among the
   frames not used yet, in capture order: frames before ``t_k - H`` are *unassigned* (they fell
   between two windows or lost a tie); of the frames inside the window, the one nearest ``t_k`` is
   the member (a tie goes to the earlier); inside frames earlier than the member are unassigned,
   later ones stay for the next window. A camera with no frame inside is missing.
3. **Steering.** After a window with members whose stamps span ``[a, b]``:
   ``t_{k+1} = t_k + P + GAIN * ((a + b) / 2 - t_k)`` with ``GAIN = 1/32``. The midrange puts
   both edges equally far from the extreme members, and a step towards it never moves a member out
   of the window, so the membership is a fixed point that only real drift can change. The
   proportional step follows the common clock: a ppm error moves the cameras by under 1 us a
   frame, which the loop tracks with a lag of about ``drift / GAIN`` (tens of us). A window
   without any member is not emitted (it says nothing) and ``t_{k+1} = t_k + P``. A run of empty
   windows is jumped over in one step (``_skip_empty``): after a frame stamped hours away (a
   clock step, a broken or hostile sender) the next window is the first one that can hold a
   frame or is not complete yet, not hours of windows closed one by one. Times in a run of empty
   windows are ``t_base + n * P`` from the last steered reference, so a run jumped in one step
   or in several gives the same float, and the online result stays equal to the batch twin's.
4. **Completion.** Window k is complete when at least one camera has delivered a frame with
   capture ``> t_k + H`` and every *live* camera has. Frames of one camera arrive in capture
   order, so nothing more can arrive for that window. A camera stops being live when ``poll(now)``
   finds it silent for more than ``max_wait_ns`` (a stalled or killed agent) or when it is removed;
   its next frame makes it live again. So a dead camera delays the rig by at most ``max_wait_ns``.
5. **Late frames.** A frame stamped at or before the end of the last closed window arrived for a
   window already closed (possible only after a timeout): it is counted in ``late_frames`` and
   not used. It is not lost: the recorder stores every frame per camera whatever the sets say.

A camera whose phase drifts across a window edge (relative drift of tens of ppm turns a phase
round in about an hour) costs at most an occasional set where it is missing plus one unassigned
frame, repeated a few times while jitter makes it flip sides at the edge; steering then recentres.

Cost: every frame enters and leaves one deque once and every window costs O(N), so thousands of
frames a second are cheap in pure Python.

Equivalence: ``group_offline`` is the slow, obvious batch twin over complete per-camera arrays
(the same rule, with numpy masks). When no timeout fires (``poll`` not called, or every camera
keeps delivering), the online result does not depend on arrival order and equals the twin's.
"""

from __future__ import annotations

import logging
import math
from bisect import insort
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from capture_agent.errors import SyncError
from protocol.errors import ConfigError

log = logging.getLogger(__name__)

MISSING = -1  # the missing marker in the session's set table
GAIN = 1.0 / 32.0  # steering gain towards each set's midrange


@dataclass(frozen=True, kw_only=True)
class SyncConfig:
    """The rig as the synchroniser sees it. ``camera_serials`` fixes the member order of sets."""

    camera_serials: tuple[int, ...]
    fps: float
    max_wait_ns: int = 500_000_000

    def __post_init__(self) -> None:
        serials = tuple(self.camera_serials)
        object.__setattr__(self, "camera_serials", serials)
        if not serials:
            raise ConfigError("SyncConfig.camera_serials is empty: list the rig's camera serials")
        for s in serials:
            if isinstance(s, bool) or not isinstance(s, int | np.integer) or s < 0:
                raise ConfigError(
                    f"SyncConfig.camera_serials contains {s!r}: serials are integers >= 0"
                )
        object.__setattr__(self, "camera_serials", tuple(int(s) for s in serials))
        dupes = sorted({s for s in self.camera_serials if self.camera_serials.count(s) > 1})
        if dupes:
            raise ConfigError(
                f"SyncConfig.camera_serials lists {dupes} more than once: each camera once"
            )
        fps = self.fps
        if isinstance(fps, bool) or not isinstance(fps, int | float) or not 0 < fps < math.inf:
            raise ConfigError(f"SyncConfig.fps={fps!r}: the frame rate must be a number > 0")
        if isinstance(self.max_wait_ns, bool) or not isinstance(self.max_wait_ns, int):
            raise ConfigError(f"SyncConfig.max_wait_ns={self.max_wait_ns!r} must be an integer")
        if self.max_wait_ns <= 0:
            raise ConfigError(
                f"SyncConfig.max_wait_ns={self.max_wait_ns}: must be > 0 ns (e.g. 500_000_000)"
            )

    @property
    def period_ns(self) -> float:
        return 1e9 / self.fps


@dataclass(frozen=True)
class SyncedSet:
    """One synchronised set. Tuples are per camera, in ``SyncConfig.camera_serials`` order.

    ``members`` holds the handle given to ``add`` for each member frame (for example its row in
    the camera's frame table), ``None`` where the camera is missing; ``capture_unix_ns`` the member
    stamps; ``set_unix_ns`` the set's reference time; ``spread_ns`` max - min of member stamps.
    """

    set_unix_ns: int
    members: tuple[int | None, ...]
    capture_unix_ns: tuple[int | None, ...]
    spread_ns: int

    def member_rows(self) -> tuple[int, ...]:
        """``members`` with ``MISSING`` (-1) for a missing camera, as the session table stores."""
        return tuple(MISSING if m is None else m for m in self.members)


def _anchor_offset(first_offsets: Sequence[int], period: float) -> float:
    """Reference time (offset from the origin) of the first window; see step 1."""
    phases = sorted(x % period for x in first_offsets)
    best_gap = phases[0] + period - phases[-1]
    centre = (phases[0] + phases[-1]) / 2.0
    for lo, hi in pairwise(phases):
        if hi - lo > best_gap:
            best_gap = hi - lo
            centre = (hi + lo + period) / 2.0
    centre %= period
    return centre - period if centre > period / 2.0 else centre


def _next_reference(t: float, lo_member: int, hi_member: int, period: float) -> float:
    """Step 3: advance one period and steer towards the members' midrange."""
    return t + period + GAIN * ((lo_member + hi_member) / 2.0 - t)


def _skip_empty(base: float, n: int, bound: float | None, period: float) -> int:
    """After the empty window ``base + n * period``: the ``n`` of the next window to look at,
    the first after it whose end (reference + half a period) reaches ``bound``. Every window
    skipped ends before ``bound`` (the earliest frame still pending, or the newest frame of
    the live camera furthest behind), so each would have closed empty, one at a time."""
    half = period / 2.0
    m = n + 1
    if bound is None or base + m * period + half >= bound:
        return m
    m = max(m, math.ceil((bound - half - base) / period))
    while base + m * period + half < bound:
        m += 1
    while m > n + 1 and base + (m - 1) * period + half >= bound:
        m -= 1
    return m


class _Camera:
    __slots__ = ("heard_ns", "newest_ns", "pending", "removed", "serial", "silent")

    def __init__(self, serial: int) -> None:
        self.serial = serial
        self.pending: deque[tuple[int, int]] = deque()  # (capture_unix_ns, handle)
        self.newest_ns: int | None = None
        self.heard_ns: int | None = None
        self.silent = False
        self.removed = False

    @property
    def live(self) -> bool:
        return not (self.silent or self.removed)


class Synchroniser:
    """Online grouping (see the module docstring). Not thread-safe: call from one thread."""

    def __init__(self, config: SyncConfig) -> None:
        self.config = config
        self._period = config.period_ns
        self._half = self._period / 2.0
        self._cams = [_Camera(s) for s in config.camera_serials]
        self._by_serial = {c.serial: c for c in self._cams}
        self._origin: int | None = None  # None until anchored
        self._t = 0.0  # current window's reference, ns after the origin: base + n * period
        self._t_base = 0.0  # the last steered reference (or the anchor)
        self._n_empty = 0  # empty windows since it
        self._closed_end = -math.inf  # end of the last closed window, ns after the origin
        self._first_heard_ns: int | None = None
        self._sets_emitted = 0
        self._unassigned = dict.fromkeys(config.camera_serials, 0)
        self._late = dict.fromkeys(config.camera_serials, 0)
        self._missing = dict.fromkeys(config.camera_serials, 0)

    # -- counters -------------------------------------------------------------------------
    @property
    def sets_emitted(self) -> int:
        return self._sets_emitted

    @property
    def unassigned_frames(self) -> dict[int, int]:
        """Per camera: frames on time that fell between windows or lost a tie (step 2)."""
        return dict(self._unassigned)

    @property
    def late_frames(self) -> dict[int, int]:
        """Per camera: frames that arrived after their window was closed (step 5)."""
        return dict(self._late)

    @property
    def missing_markers(self) -> dict[int, int]:
        """Per camera: emitted sets in which the camera is missing."""
        return dict(self._missing)

    @property
    def reference_unix_ns(self) -> int | None:
        """The open window's reference time, or None before the anchor."""
        return None if self._origin is None else self._origin + round(self._t)

    @property
    def live_cameras(self) -> tuple[int, ...]:
        """Cameras that windows wait for (not silent past ``max_wait_ns``, not removed)."""
        return tuple(c.serial for c in self._cams if c.live)

    # -- input ----------------------------------------------------------------------------
    def add(
        self,
        camera_serial: int,
        capture_unix_ns: int,
        handle: int,
        receive_unix_ns: int | None = None,
    ) -> list[SyncedSet]:
        """Take one frame; return the sets it completes.

        ``receive_unix_ns`` is when the frame reached the recorder, on the clock later given to
        ``poll``; without it the capture stamp stands in (fine when the recorder's clock is
        PTP-disciplined too, since latency is far below ``max_wait_ns``).
        """
        cam = self._by_serial.get(int(camera_serial))
        if cam is None:
            raise SyncError(
                f"frame from camera {camera_serial}, which is not in the rig "
                f"{list(self.config.camera_serials)}; add it to rig.toml"
            )
        capture = int(capture_unix_ns)
        heard = capture if receive_unix_ns is None else int(receive_unix_ns)
        cam.heard_ns = heard
        if self._first_heard_ns is None:
            self._first_heard_ns = heard
        if not cam.live:
            log.info("camera %d delivers again; sets wait for it from now on", cam.serial)
            cam.silent = cam.removed = False
        origin = self._origin
        if origin is not None and capture - origin <= self._closed_end:
            self._late[cam.serial] += 1
            if cam.newest_ns is None or capture > cam.newest_ns:
                cam.newest_ns = capture
            return []
        if cam.newest_ns is None or capture >= cam.newest_ns:
            cam.pending.append((capture, int(handle)))
            cam.newest_ns = capture
        else:  # out of capture order (a clock step): rare, keep the deque sorted
            insort(cam.pending, (capture, int(handle)))
        if origin is None:
            return self._drain() if self._try_anchor() else []
        if capture - origin > self._t + self._half:
            return self._drain()
        return []

    def poll(self, now_unix_ns: int) -> list[SyncedSet]:
        """Mark cameras silent for more than ``max_wait_ns``; return the sets that completes."""
        now = int(now_unix_ns)
        if self._first_heard_ns is None:
            self._first_heard_ns = now
        for cam in self._cams:
            if not cam.live:
                continue
            last = cam.heard_ns if cam.heard_ns is not None else self._first_heard_ns
            if now - last > self.config.max_wait_ns:
                cam.silent = True
                log.warning(
                    "camera %d silent for %.0f ms; sets no longer wait for it",
                    cam.serial,
                    (now - last) / 1e6,
                )
        if self._origin is None and not self._try_anchor():
            return []
        return self._drain()

    def remove_camera(self, camera_serial: int) -> list[SyncedSet]:
        """Stop waiting for a camera now (its agent left); its next frame brings it back."""
        cam = self._by_serial.get(int(camera_serial))
        if cam is None:
            raise SyncError(f"camera {camera_serial} is not in the rig")
        cam.removed = True
        if self._origin is None and not self._try_anchor():
            return []
        return self._drain()

    def flush(self) -> list[SyncedSet]:
        """At stop: close every window that still holds a pending frame."""
        if self._origin is None and not self._try_anchor(force=True):
            return []
        return self._drain(flush=True)

    # -- internals ------------------------------------------------------------------------
    def _try_anchor(self, force: bool = False) -> bool:
        with_frames = [c for c in self._cams if c.pending]
        if not with_frames:
            return False
        if not force and any(c.live and not c.pending for c in self._cams):
            return False
        firsts = [c.pending[0][0] for c in with_frames]
        origin = min(firsts)
        self._t = self._t_base = _anchor_offset([f - origin for f in firsts], self._period)
        self._n_empty = 0
        self._origin = origin
        log.debug("anchored at %d ns from %d cameras", origin + round(self._t), len(firsts))
        return True

    def _complete(self) -> bool:
        assert self._origin is not None
        origin, end = self._origin, self._t + self._half
        passed = False
        for cam in self._cams:
            if cam.newest_ns is not None and cam.newest_ns - origin > end:
                passed = True
            elif cam.live:
                return False
        return passed

    def _drain(self, flush: bool = False) -> list[SyncedSet]:
        out: list[SyncedSet] = []
        while True:
            if flush:
                if not any(c.pending for c in self._cams):
                    break
            elif not self._complete():
                break
            s = self._close_window(flush)
            if s is not None:
                out.append(s)
        return out

    def _close_window(self, flush: bool = False) -> SyncedSet | None:
        origin = self._origin
        assert origin is not None
        t = self._t
        lo, hi = t - self._half, t + self._half
        self._closed_end = hi
        members: list[int | None] = []
        stamps: list[int | None] = []
        for cam in self._cams:
            q = cam.pending
            while q and q[0][0] - origin < lo:
                q.popleft()
                self._unassigned[cam.serial] += 1
            best, best_d, i = -1, math.inf, 0
            while i < len(q) and q[i][0] - origin <= hi:
                d = abs((q[i][0] - origin) - t)
                if d < best_d:
                    best, best_d = i, d
                i += 1
            if best < 0:
                members.append(None)
                stamps.append(None)
                continue
            for _ in range(best):
                q.popleft()
                self._unassigned[cam.serial] += 1
            capture, handle = q.popleft()
            members.append(handle)
            stamps.append(capture)
        present = [s for s in stamps if s is not None]
        if not present:
            self._n_empty = _skip_empty(
                self._t_base, self._n_empty, self._skip_bound(flush), self._period
            )
            self._t = self._t_base + self._n_empty * self._period
            # the windows skipped are closed too: a frame for one of them is late (step 5)
            last_skipped = self._t_base + (self._n_empty - 1) * self._period
            self._closed_end = max(hi, last_skipped + self._half)
            return None
        a, b = min(present), max(present)
        self._t = self._t_base = _next_reference(t, a - origin, b - origin, self._period)
        self._n_empty = 0
        self._sets_emitted += 1
        for cam, m in zip(self._cams, members, strict=True):
            if m is None:
                self._missing[cam.serial] += 1
        return SyncedSet(origin + round(t), tuple(members), tuple(stamps), b - a)

    def _skip_bound(self, flush: bool) -> float | None:
        """How far empty windows may be skipped (offsets from the origin): up to the earliest
        pending frame and, unless flushing, the newest frame of the live camera furthest
        behind (a later window is not complete yet)."""
        assert self._origin is not None
        origin = self._origin
        bounds = [c.pending[0][0] - origin for c in self._cams if c.pending]
        if not flush:
            bounds += [
                c.newest_ns - origin for c in self._cams if c.live and c.newest_ns is not None
            ]
        return float(min(bounds)) if bounds else None


def group_offline(stamps_by_camera: Mapping[int, np.ndarray], fps: float) -> list[SyncedSet]:
    """The slow, obvious batch twin of ``Synchroniser`` (same rule, every window a numpy scan).

    ``stamps_by_camera`` maps serial -> int64 capture stamps (Unix ns), in capture order; the
    member handles are indices into those arrays. Cameras come in the mapping's order.
    """
    serials = list(stamps_by_camera)
    SyncConfig(camera_serials=tuple(serials), fps=fps)  # the same validation
    arrays = [np.asarray(stamps_by_camera[s], dtype=np.int64) for s in serials]
    if any(np.any(np.diff(a) < 0) for a in arrays):
        raise ValueError("group_offline: each camera's stamps must be in capture order")
    firsts = [int(a[0]) for a in arrays if a.size]
    if not firsts:
        return []
    period = 1e9 / fps
    half = period / 2.0
    origin = min(firsts)
    t = base = _anchor_offset([f - origin for f in firsts], period)
    n_empty = 0
    offsets = [a - origin for a in arrays]
    used = [np.zeros(a.size, bool) for a in arrays]
    out: list[SyncedSet] = []
    while any(np.any(~u & (x >= t - half)) for x, u in zip(offsets, used, strict=True)):
        lo, hi = t - half, t + half
        members: list[int | None] = []
        stamps: list[int | None] = []
        for x, u, a in zip(offsets, used, arrays, strict=True):
            candidates = np.flatnonzero(~u & (x >= lo) & (x <= hi))
            if candidates.size == 0:
                members.append(None)
                stamps.append(None)
                continue
            j = int(candidates[np.argmin(np.abs(x[candidates] - t))])
            u[j] = True
            members.append(j)
            stamps.append(int(a[j]))
        present = [s for s in stamps if s is not None]
        if not present:
            later = [x[~u & (x > hi)] for x, u in zip(offsets, used, strict=True)]
            bound = min((float(v.min()) for v in later if v.size), default=None)
            n_empty = _skip_empty(base, n_empty, bound, period)
            t = base + n_empty * period
            continue
        a_min, b_max = min(present), max(present)
        out.append(SyncedSet(origin + round(t), tuple(members), tuple(stamps), b_max - a_min))
        t = base = _next_reference(t, a_min - origin, b_max - origin, period)
        n_empty = 0
    return out


def unassigned_offline(
    stamps_by_camera: Mapping[int, np.ndarray], sets: Iterable[SyncedSet]
) -> dict[int, int]:
    """Per camera, how many frames no set uses (the twin of ``Synchroniser.unassigned_frames``)."""
    serials = list(stamps_by_camera)
    used = dict.fromkeys(serials, 0)
    for s in sets:
        for serial, m in zip(serials, s.members, strict=True):
            used[serial] += m is not None
    return {s: len(stamps_by_camera[s]) - used[s] for s in serials}
