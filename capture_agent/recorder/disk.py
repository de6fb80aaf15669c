"""The disk the sessions go to, as the recorder's I/O thread sees it (``recorder.py``): its free
space, measured every ``DISK_CHECK_S``, and the reserve (``disk_reserve_gb``) a take must never
eat into. A take is stopped while there is still room for what arrives before the next checks
and for closing the file (``DISK_HEADROOM_S`` at the take's rate). That rate is planned from
the configuration (each camera's fps x its typical frame, ``CameraTable.planned_byte_rate``), or
the take's sustained write rate if higher; never a burst's, which the cameras' caps refuse anyway
and which would otherwise stop every node's take."""

from __future__ import annotations

import shutil
from pathlib import Path

DISK_CHECK_S = 0.25
DISK_HEADROOM_S = 3.0  # seconds of recording kept free above the reserve
CLOSE_HEADROOM_BYTES = 8e6  # room to close the file


class DiskBudget:
    """The output folder's free space and its reserve."""

    def __init__(self, *, output_dir: str, reserve_gb: float) -> None:
        self.output_dir = output_dir
        self.reserve_gb = reserve_gb
        self.free_bytes = self.measure()  # as last checked; ``status`` shows it
        self._last_check_monotonic = 0.0

    @property
    def reserve_bytes(self) -> float:
        return self.reserve_gb * 1e9

    def measure(self) -> int:
        """The free bytes now, of the folder or (before it exists) its nearest parent."""
        target = Path(self.output_dir)
        probe = target if target.exists() else target.parent
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        return shutil.disk_usage(probe).free

    def check_due(self, now_monotonic: float) -> bool:
        """Measure again if ``DISK_CHECK_S`` passed since the last check; whether it did."""
        if now_monotonic - self._last_check_monotonic < DISK_CHECK_S:
            return False
        self._last_check_monotonic = now_monotonic
        self.free_bytes = self.measure()
        return True

    def near_reserve(self, rate_bytes_per_s: float) -> bool:
        """Whether the last measured free space leaves under ``DISK_HEADROOM_S`` of recording
        at ``rate_bytes_per_s`` (and room to close the file) above the reserve."""
        headroom = DISK_HEADROOM_S * rate_bytes_per_s + CLOSE_HEADROOM_BYTES
        return self.free_bytes < self.reserve_bytes + headroom
