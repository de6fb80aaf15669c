"""What one camera's stream may bring the recorder: its frame rate and bytes, held to what the
rig says the camera is (``intake.CameraTable`` applies it to every frame it accepts).

Why. A node with a valid key, compromised or buggy, can send far more than its cameras capture.
Without a bound, one node's burst fills the take's write queue (everyone's frames are then
refused) and looks to the disk check like a rate that will fill the disk. So each camera has two
token buckets: frames at ``RATE_CAP_FACTOR`` x its fps, and bytes at ``RATE_CAP_FACTOR`` x its
fps x its largest frame (both images of its mode, raw, at most rig.toml's ``max_image_bytes``
each). Each holds ``BURST_S`` of its rate, so the jitter of a healthy stream never touches it.

The buckets' clock. They refill by the frames' capture stamps, not by arrival: frames that were
queued in the link (a recorder that paused, a network that caught up) arrive together but carry
their real stamps, one frame period apart, so a healthy backlog is never refused. A sender cannot
gain by stamping ahead: the clock is the stamp or the recorder's clock plus ``STAMP_LEAD_S``,
whichever is earlier, so tokens never accrue faster than real time (plus that lead). Stamps that
go back are refused before the buckets (``CameraTable.accept_frame``), so the clock only advances.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol.session import EventKind

RATE_CAP_FACTOR = 1.5  # of the configured fps: above it, frames are refused
BURST_S = 1.0  # each bucket holds this long of its rate
STAMP_LEAD_S = 0.5  # a stamp ahead of the recorder's clock counts as this far ahead at most


@dataclass(frozen=True, kw_only=True)
class StreamLimits:
    """A camera's configured rate and its largest frame (both images, bytes)."""

    fps: float
    largest_frame_bytes: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be a number > 0, got {self.fps}")
        if self.largest_frame_bytes < 1:
            raise ValueError(f"largest_frame_bytes must be >= 1, got {self.largest_frame_bytes}")

    @property
    def max_frames_per_s(self) -> float:
        return RATE_CAP_FACTOR * self.fps

    @property
    def max_bytes_per_s(self) -> float:
        return RATE_CAP_FACTOR * self.fps * self.largest_frame_bytes


class TokenBucket:
    """``rate_per_s`` tokens a second, at most ``depth``; starts full."""

    __slots__ = ("clock_ns", "depth", "rate_per_s", "tokens")

    def __init__(self, rate_per_s: float, depth: float) -> None:
        self.rate_per_s, self.depth = rate_per_s, depth
        self.tokens = depth
        self.clock_ns: int | None = None

    def refill(self, clock_ns: int) -> None:
        if self.clock_ns is not None and clock_ns > self.clock_ns:
            gained = (clock_ns - self.clock_ns) / 1e9 * self.rate_per_s
            self.tokens = min(self.depth, self.tokens + gained)
        if self.clock_ns is None or clock_ns > self.clock_ns:
            self.clock_ns = clock_ns


class StreamBudget:
    """One camera's two buckets (frames, bytes); ``admit`` says whether a frame fits."""

    __slots__ = ("bytes", "frames", "limits")

    def __init__(self, limits: StreamLimits) -> None:
        self.limits = limits
        self.frames = TokenBucket(limits.max_frames_per_s, limits.max_frames_per_s * BURST_S)
        self.bytes = TokenBucket(
            limits.max_bytes_per_s,
            max(limits.max_bytes_per_s * BURST_S, float(limits.largest_frame_bytes)),
        )

    def admit(self, nbytes: int, capture_unix_ns: int, rx_unix_ns: int) -> EventKind | None:
        """None when the frame fits (its tokens are taken), else why not: ``RATE_CAPPED`` or
        ``BYTES_CAPPED`` (nothing is taken)."""
        clock_ns = min(capture_unix_ns, rx_unix_ns + int(STAMP_LEAD_S * 1e9))
        self.frames.refill(clock_ns)
        self.bytes.refill(clock_ns)
        if self.frames.tokens < 1.0:
            return EventKind.RATE_CAPPED
        if self.bytes.tokens < nbytes:
            return EventKind.BYTES_CAPPED
        self.frames.tokens -= 1.0
        self.bytes.tokens -= nbytes
        return None
