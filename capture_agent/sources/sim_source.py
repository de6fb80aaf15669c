"""The simulated ZED X: a real camera source backed by ``sim.World``, with known truth.

Timing follows the camera's own free-running clock (``sim.timing.FrameClock``) exactly: frame
``i`` is exposed at sim time ``phase + i * period`` and stamped
``epoch_unix_ns + exposure + readout latency + jitter``; frames the clock marks as dropped are
never returned, so ``frame_index`` jumps as on real hardware. ``truth()`` gives the same numbers
for any time range, to check the capture path against.

Sim time 0 is ``epoch_unix_ns``. Every agent of one rig must use the same epoch, or their stamps
are not on one timeline (real PTP-disciplined clocks are). The default, the start of the current
UTC day (computed once, at the first ``open()``), suits a single process; agents started around
midnight UTC would disagree, so a rig (and every multi-process test) sets ``epoch_unix_ns``.

Rendering is slow (SVGA stereo about 0.25 s, HD1200 about 0.8 s on 2 cores), so image *content*
is rendered ``content_fps`` times per sim second, while stamps and indices run at ``fps``; each
frame shows the content of ``floor(exposure * content_fps) / content_fps``. With ``content_fps``
equal to ``fps`` every frame shows the scene at its own exposure time, as a real camera does:
what calibration and reconstruction tests need, since cameras of one set expose at slightly
different times. With ``prerender_s = N`` the content of sim time ``[0, N)`` is rendered before
``open()`` returns and then loops (content time = sim time mod N, the same for every agent of a
rig), so streaming costs no rendering (the benchmark's mode); looped frame-exact content needs
clocks without drift to repeat exactly, so such cameras run at the nominal rate (``clock_spec``).
With ``prerender_s = 0`` a background thread renders just ahead of the clock and a lagging frame
reuses the most recent content rather than stalling the clock.

With ``realtime = true`` (the default) ``grab()`` sleeps until the wall clock reaches the next
frame's stamp; like the SDK's small frame buffer, a consumer more than ``BUFFER_S`` late loses the
oldest frames (counted in ``overrun_frames``). With ``realtime = false`` frames come as fast as
they are asked for, with the same stamps.

Faults, for watchdog tests, start ``at_s`` seconds after the first ``open()`` returned:
``hang`` delivers nothing for ``duration_s`` (``grab()`` times out); ``vanish`` makes ``grab()``
and ``open()`` raise ``CameraUnavailableError`` until it is over, then a reopen works. Frames
stamped inside a fault window are lost.

Example ``node.toml`` table::

    [[cameras]]
    source = "sim"
    seed = 11
    camera_index = 0
    resolution = "SVGA"
    epoch_unix_ns = 1767225600000000000
    faults = [{ kind = "hang", at_s = 10.0, duration_s = 2.0 }]
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from capture_agent.errors import CameraUnavailableError
from capture_agent.sources.base import CameraSource, GrabbedFrame, require_timeout
from protocol.camera import Resolution
from protocol.errors import ConfigError
from protocol.formats.camera_config import FaultSpec, SimSourceConfig
from protocol.images import EncodedPair, encode_pair

if TYPE_CHECKING:
    from sim.timing import ClockSpec, FrameClock, FrameTruth
    from sim.world import World

log = logging.getLogger(__name__)

BUFFER_S = 0.5  # frames older than this when grab() is called are lost (a camera's buffer)
DAY_NS = 86_400 * 1_000_000_000
_CONTENT_CACHE = 4  # lazily rendered content frames kept (current, next, and a little slack)

# One render at a time per process: the kernels already use every core, and two sources of one
# node share a World.
_RENDER_LOCK = threading.Lock()
_WORLD_LOCK = threading.Lock()
_WORLDS: dict[tuple[int, str], World] = {}


def shared_world(seed: int, phase: str) -> World:
    """One ``World`` per (seed, phase) per process, shared by the sources of one node."""
    from sim import World

    with _WORLD_LOCK:
        key = (seed, phase)
        if key not in _WORLDS:
            _WORLDS[key] = World.from_seed(seed, phase=phase)
        return _WORLDS[key]


def start_of_utc_day(unix_ns: int) -> int:
    """Midnight UTC of the day containing ``unix_ns`` (Unix time has no leap seconds)."""
    return unix_ns - unix_ns % DAY_NS


def clock_spec(config: SimSourceConfig) -> ClockSpec:
    """The free-running clock of a sim camera with ``config``."""
    from sim.timing import ClockSpec

    # Looped, frame-exact content repeats exactly only if every camera's period divides
    # the loop; with a clock drift of p ppm, loop n would show content n * N * p seconds
    # away from the frame's stamp, different for each camera (12 ms after 300 s at 40 ppm
    # apart: 5 mm of a waved wand). Such cameras keep their random phase, jitter and drops,
    # but run at the nominal rate.
    looped_exact = config.prerender_s > 0 and config.content_fps >= config.fps
    return ClockSpec(
        fps=config.fps,
        free_running=config.free_running,
        jitter_ns_std=config.jitter_ns_std,
        drop_probability=config.drop_probability,
        max_abs_ppm=0.0 if looped_exact else 20.0,
    )


@dataclass(frozen=True)
class _Content:
    left_bgr: np.ndarray | None
    right_bgr: np.ndarray | None
    encoded: EncodedPair | None


class SimSource(CameraSource):
    """One simulated ZED X of ``sim.World``'s rig. ``grab()`` is for one consumer thread."""

    def __init__(self, config: SimSourceConfig, *, world: World | None = None) -> None:
        if world is not None and (world.config.seed, world.config.phase) != (
            config.seed,
            config.phase,
        ):
            raise ValueError(
                f"the world (seed {world.config.seed}, phase {world.config.phase!r}) is not the "
                f"configured one (seed {config.seed}, phase {config.phase!r})"
            )
        self.config = config
        self._world = world
        self._epoch_unix_ns = config.epoch_unix_ns
        self._fault_anchor_unix_ns: int | None = None
        self._clock: FrameClock | None = None
        self._open = False
        self._vanished = False
        self._pending: collections.deque[tuple[int, float, int]] = collections.deque()
        self._window_t_s = 0.0
        self._content: dict[int, _Content] = {}
        self._content_lock = threading.Lock()
        self._loop: tuple[int, int] | None = None  # (first content index, count) when prerendered
        self._render_s = 0.3
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.delivered_frames = 0
        self.dropped_frames = 0  # by the camera (the clock's truth)
        self.overrun_frames = 0  # lost because grab() was called too late
        self.fault_frames = 0  # lost inside a fault window

    # ---- identity ------------------------------------------------------------------------
    @property
    def world(self) -> World:
        if self._world is None:
            self._world = shared_world(self.config.seed, self.config.phase)
        return self._world

    @property
    def serial(self) -> int:
        return self.world.rig[self.config.camera_index].serial

    @property
    def resolution(self) -> Resolution:
        return self.config.resolution

    @property
    def fps(self) -> float:
        return self.config.fps

    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def epoch_unix_ns(self) -> int:
        if self._epoch_unix_ns is None:
            raise RuntimeError(
                f"{self.name}: epoch_unix_ns is chosen at open(); open the source or set it"
            )
        return self._epoch_unix_ns

    @property
    def clock(self) -> FrameClock:
        """The camera's frame clock (the truth behind every stamp)."""
        if self._clock is None:
            self._clock = self.world.clock(
                self.config.camera_index, clock_spec(self.config), self.epoch_unix_ns
            )
        return self._clock

    def factory_conf_text(self) -> str:
        return self.world.rig[self.config.camera_index].factory.to_text()

    def truth(self, t0_unix_ns: int, t1_unix_ns: int) -> FrameTruth:
        """The clock's frames whose mid-exposure time ``epoch + exposure_t_s`` is in
        ``[t0_unix_ns, t1_unix_ns)``, dropped ones included (``dropped`` marks them)."""
        epoch = self.epoch_unix_ns
        t0 = max(0.0, (int(t0_unix_ns) - epoch) / 1e9)
        t1 = max(t0, (int(t1_unix_ns) - epoch) / 1e9)
        return self.clock.frames(t0, t1)

    # ---- life cycle ----------------------------------------------------------------------
    def open(self) -> None:
        if self._open and not self._vanished:
            return
        self.close()
        now_ns = time.time_ns()
        if self._epoch_unix_ns is None:
            self._epoch_unix_ns = start_of_utc_day(now_ns)
            log.info(
                "%s: epoch_unix_ns not set; using the start of today (UTC), %d",
                self.name,
                self._epoch_unix_ns,
            )
        if self._epoch_unix_ns > now_ns:
            raise ConfigError(
                f"epoch_unix_ns = {self._epoch_unix_ns} is in the future; sim time 0 must be "
                "at or before now"
            )
        fault = self._fault_at(now_ns)
        if fault is not None and fault[0].kind == "vanish":
            raise CameraUnavailableError(f"{self.name} is not connected (simulated 'vanish')")
        _ = self.clock
        if self.config.prerender_s > 0:
            # content of sim time [0, N), the same window for every agent, then looping
            count = self._loop_count()
            t_start = time.perf_counter()
            for key in range(count):
                self._content[key] = self._render(key)
            log.info(
                "%s: prerendered %d content frames in %.1f s",
                self.name,
                count,
                time.perf_counter() - t_start,
            )
            self._loop = (0, count)
        else:
            first = self._content_index(self._sim_now_s())
            self._content[first] = self._render(first)
        self._vanished = False
        self._pending.clear()
        self._window_t_s = self._sim_now_s()  # frames start after the (slow) rendering above
        if self._fault_anchor_unix_ns is None:  # fault times count from the end of the first open
            self._fault_anchor_unix_ns = time.time_ns()
        self._open = True
        if self._loop is None and self.config.realtime:
            self._stop.clear()
            self._thread = threading.Thread(
                target=self._render_ahead, name=f"sim-render-SN{self.serial}", daemon=True
            )
            self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._content_lock:
            self._content.clear()
        self._loop = None
        self._pending.clear()
        self._open = False

    # ---- frames --------------------------------------------------------------------------
    def grab(self, timeout_s: float) -> GrabbedFrame | None:
        if not self._open:
            raise RuntimeError(f"{self.name} is not open; call open() first")
        deadline = time.monotonic() + require_timeout(timeout_s)
        while True:
            now_ns = time.time_ns()
            fault = self._fault_at(now_ns)
            if self._vanished or (fault is not None and fault[0].kind == "vanish"):
                self._vanished = True
                raise CameraUnavailableError(f"{self.name} vanished (simulated); reopen it later")
            remaining = deadline - time.monotonic()
            if fault is not None:  # hang: nothing arrives until it ends
                left = (fault[1] - now_ns) / 1e9
                if remaining < left:
                    time.sleep(max(remaining, 0.0))
                    return None
                time.sleep(left)
                continue
            index, exposure_t_s, capture_ns = self._next_frame(now_ns)
            wait = (capture_ns - now_ns) / 1e9 if self.config.realtime else 0.0
            if wait > 0:
                step = min(wait, self._until_next_fault(now_ns))
                if remaining < step:
                    time.sleep(max(remaining, 0.0))
                    return None
                time.sleep(step)
                continue
            self._pending.popleft()
            host_receive_unix_ns = time.time_ns()
            content = self._content_for(exposure_t_s)
            self.delivered_frames += 1
            return GrabbedFrame(
                frame_index=index,
                capture_unix_ns=capture_ns,
                host_receive_unix_ns=host_receive_unix_ns,
                left_bgr=content.left_bgr,
                right_bgr=content.right_bgr,
                encoded=content.encoded,
            )

    def _sim_now_s(self) -> float:
        return max(0.0, (time.time_ns() - self.epoch_unix_ns) / 1e9)

    def _next_frame(self, now_ns: int) -> tuple[int, float, int]:
        """The next deliverable frame (left in the queue): dropped, stale and faulted ones go."""
        while True:
            while not self._pending:
                truth = self.clock.frames(self._window_t_s, self._window_t_s + 1.0)
                self._window_t_s += 1.0
                self.dropped_frames += int(truth.dropped.sum())
                keep = ~truth.dropped
                self._pending.extend(
                    zip(
                        truth.frame_index[keep].tolist(),
                        truth.exposure_t_s[keep].tolist(),
                        truth.capture_unix_ns[keep].tolist(),
                        strict=True,
                    )
                )
            frame = self._pending[0]
            if self._in_fault_window(frame[2]):
                self.fault_frames += 1
            elif self.config.realtime and frame[2] < now_ns - BUFFER_S * 1e9:
                self.overrun_frames += 1
            else:
                return frame
            self._pending.popleft()

    # ---- faults --------------------------------------------------------------------------
    def fault_windows_unix_ns(self) -> list[tuple[str, int, int]]:
        """(kind, start, end) of each configured fault; empty before the first ``open()``."""
        return [(f.kind, start, end) for f, start, end in self._fault_windows()]

    def _fault_windows(self) -> list[tuple[FaultSpec, int, int]]:
        anchor = self._fault_anchor_unix_ns
        if anchor is None:
            return []
        return [
            (f, anchor + round(f.at_s * 1e9), anchor + round((f.at_s + f.duration_s) * 1e9))
            for f in self.config.faults
        ]

    def _fault_at(self, unix_ns: int) -> tuple[FaultSpec, int] | None:
        """The fault active at ``unix_ns`` (vanish first) and when it ends."""
        active = [(f, end) for f, start, end in self._fault_windows() if start <= unix_ns < end]
        active.sort(key=lambda fe: fe[0].kind != "vanish")
        return active[0] if active else None

    def _in_fault_window(self, unix_ns: int) -> bool:
        return any(start <= unix_ns < end for _, start, end in self._fault_windows())

    def _until_next_fault(self, now_ns: int) -> float:
        starts = [start for _, start, _ in self._fault_windows() if start > now_ns]
        return (min(starts) - now_ns) / 1e9 if starts else math.inf

    # ---- content -------------------------------------------------------------------------
    def _key(self, content_index: int) -> int:
        if self._loop is None:
            return content_index
        first, count = self._loop
        return first + (content_index - first) % count

    @property
    def _exact(self) -> bool:
        """One content frame per camera frame, at its exact exposure time."""
        return self.config.content_fps >= self.config.fps

    def _loop_count(self) -> int:
        rate = self.config.fps if self._exact else self.config.content_fps
        return max(1, math.ceil(self.config.prerender_s * rate))

    def _content_index(self, exposure_t_s: float) -> int:
        if self._exact:  # the frame's own index: its content is rendered at its exposure time
            return max(0, round((exposure_t_s - self.clock.exposure_time(0)) / self.clock.period_s))
        return math.floor(exposure_t_s * self.config.content_fps)

    def _content_time_s(self, key: int) -> float:
        if self._exact:
            return self.clock.exposure_time(key)
        return key / self.config.content_fps

    def _render(self, key: int) -> _Content:
        t_s = self._content_time_s(key)
        t0 = time.perf_counter()
        with _RENDER_LOCK:
            left, right = self.world.render_stereo(
                self.config.camera_index, t_s, self.config.resolution
            )
        self._render_s = time.perf_counter() - t0
        left_bgr = cv2.cvtColor(left.image_rgb, cv2.COLOR_RGB2BGR)
        right_bgr = cv2.cvtColor(right.image_rgb, cv2.COLOR_RGB2BGR)
        if self.config.pre_encode is not None:
            pair = encode_pair(
                left_bgr, right_bgr, self.config.pre_encode, self.config.jpeg_quality
            )
            return _Content(None, None, pair)  # keep only the bytes: prerendering stays small
        left_bgr.flags.writeable = False
        right_bgr.flags.writeable = False
        return _Content(left_bgr, right_bgr, None)

    def _content_for(self, exposure_t_s: float) -> _Content:
        key = self._key(self._content_index(exposure_t_s))
        with self._content_lock:
            content = self._content.get(key)
            if content is not None:
                return content
            if self.config.realtime:  # lagging: the most recent content, never a stall
                older = [k for k in self._content if k <= key]
                return self._content[max(older) if older else min(self._content)]
        content = self._render(key)  # not realtime: render on demand, deterministic
        self._store(key, content)
        return content

    def _store(self, key: int, content: _Content) -> None:
        with self._content_lock:
            self._content[key] = content
            for old in sorted(self._content)[: max(0, len(self._content) - _CONTENT_CACHE)]:
                del self._content[old]

    def _render_ahead(self) -> None:
        """Keep the content that will be current when a render finishes ready (realtime)."""
        while not self._stop.is_set():
            now_t = self._sim_now_s()
            target = self._content_index(now_t + self._render_s)
            with self._content_lock:
                todo = [k for k in (target, target + 1) if k not in self._content]
            if todo:
                try:
                    self._store(todo[0], self._render(todo[0]))
                except Exception:  # keep streaming the last content; the log says why
                    log.exception("%s: rendering content frame %d failed", self.name, todo[0])
                    self._stop.wait(1.0)
                continue
            wake = self._content_time_s(target + 1) - self._render_s - now_t
            self._stop.wait(min(max(wake, 0.005), 0.5))
