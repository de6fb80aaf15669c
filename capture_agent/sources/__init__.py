"""Camera sources: the ``CameraSource`` seam and its backends.

- ``sim``: a simulated ZED X of ``sim.World``'s rig, with ground truth (``sim_source.py``);
- ``zed``: a real ZED X through the ZED SDK's ``pyzed`` (``zed_source.py``);
- ``video``: a recorded stereo video replayed through OpenCV (``video_source.py``).

``make_source`` imports a backend only when it is asked for, so a Jetson without the simulator's
libraries runs ``zed``, and a laptop without the ZED SDK runs ``sim``; a missing SDK fails with
a message that names what to install.

Example::

    from capture_agent.sources import make_source
    cam = make_source("sim", {"camera_index": 1, "resolution": "SVGA"}, "node.toml [[cameras]] #2")
    with cam:
        frame = cam.grab(timeout_s=1.0)
"""

from __future__ import annotations

from typing import Any

from capture_agent.sources.base import (
    CameraSource,
    CameraUnavailableError,
    EndOfRecordingError,
    GrabbedFrame,
)
from protocol.errors import ConfigError

SOURCE_KINDS = ("sim", "zed", "video")

__all__ = [
    "SOURCE_KINDS",
    "CameraSource",
    "CameraUnavailableError",
    "EndOfRecordingError",
    "GrabbedFrame",
    "make_source",
]


def make_source(kind: str, table: dict[str, Any], where: str) -> CameraSource:
    """Build the ``kind`` source from its TOML table; ``where`` names the file and table in errors.

    Raises ``ConfigError`` for an unknown kind or a bad option, and ``zed_source.SdkMissingError``
    (a ``UserError``) when ``kind = "zed"`` and pyzed is not installed.
    """
    if kind == "sim":
        from capture_agent.sources.sim_source import SimSource, SimSourceConfig

        return SimSource(SimSourceConfig.from_table(table, where))
    if kind == "zed":
        from capture_agent.sources.zed_source import ZedSource, ZedSourceConfig

        return ZedSource(ZedSourceConfig.from_table(table, where))
    if kind == "video":
        from capture_agent.sources.video_source import VideoSource, VideoSourceConfig

        return VideoSource(VideoSourceConfig.from_table(table, where))
    kinds = ", ".join(repr(k) for k in SOURCE_KINDS)
    raise ConfigError(f"{where}: unknown camera source {kind!r}; choose one of {kinds}")
