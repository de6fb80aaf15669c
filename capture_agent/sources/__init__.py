"""Camera sources: the ``CameraSource`` seam and its backends.

- ``sim``: a simulated ZED X of ``sim.World``'s rig, with ground truth (``sim_source.py``);
- ``zed``: a real ZED X through the ZED SDK's ``pyzed`` (``zed_source.py``);
- ``video``: a recorded stereo video replayed through OpenCV (``video_source.py``).

``make_source`` imports a backend only when it is asked for, so a Jetson without the simulator's
libraries runs ``zed``, and a laptop without the ZED SDK runs ``sim``; a missing SDK fails with
a message that names what to install.

A source takes its checked config (``protocol/formats/camera_config.py``: one dataclass per backend,
read from node.toml's ``[[cameras]]`` tables when the node config loads).

Example::

    from protocol.formats.camera_config import SimSourceConfig
    from capture_agent.sources import make_source
    with make_source(SimSourceConfig(camera_index=1)) as cam:
        frame = cam.grab(timeout_s=1.0)
"""

from __future__ import annotations

from capture_agent.sources.base import CameraSource, GrabbedFrame
from protocol.formats.camera_config import CameraConfig

__all__ = [
    "CameraSource",
    "GrabbedFrame",
    "make_source",
]


def make_source(config: CameraConfig) -> CameraSource:
    """The source that ``config`` (a ``[[cameras]]`` table, read and checked) describes.

    Raises ``capture_agent.errors.SdkMissingError`` (a ``UserError``) for a ZED camera where
    pyzed is not installed.
    """
    if config.source == "sim":
        from capture_agent.sources.sim_source import SimSource

        return SimSource(config)
    if config.source == "zed":
        from capture_agent.sources.zed_source import ZedSource

        return ZedSource(config)
    from capture_agent.sources.video_source import VideoSource

    return VideoSource(config)
