"""``egosurg shell``: a ptpython console for operators with a connected ``rig``.

Example::

    egosurg shell --recorder tcp://10.10.0.5:5560
    >>> rig.status()                       # the same table as 'egosurg status'
    >>> rig.start("case-0042", surgeon="A. Smith")
    >>> img = rig.last_frame(41234567)     # a BGR numpy image from the live stream
    >>> rig.save_frame(41234567, "check.png")
    >>> rig.stop()
"""

from __future__ import annotations

import argparse
from typing import Any

import cv2
import numpy as np

from capture_agent.control import format_status, format_summary
from capture_agent.rig_client import RigClient

BANNER = """EgoSurg operator console. The object 'rig' is connected to {url}:
  rig.status()                      health of every camera, PTP and disk
  rig.start("case-name", key=value) start recording a case (metadata as keywords)
  rig.stop()                        stop and print the session summary
  rig.last_frame(serial)            the camera's latest image (BGR numpy array)
  rig.save_frame(serial, "f.png")   save it as a picture
"""


class Rig:
    """What the console's ``rig`` does: the RigClient, with readable results."""

    def __init__(self, client: RigClient) -> None:
        self.client = client

    def status(self) -> StatusView:
        return StatusView(self.client.status())

    def start(self, case: str, planned_duration_min: float | None = None, **meta: str) -> dict:
        return self.client.start(case, planned_duration_min, **meta)

    def stop(self) -> SummaryView:
        return SummaryView(self.client.stop())

    def last_frame(self, camera: int, side: str = "left") -> np.ndarray:
        return self.client.last_frame(camera, side)

    def save_frame(self, camera: int, path: str, side: str = "left") -> str:
        if not cv2.imwrite(path, self.last_frame(camera, side)):
            raise OSError(f"could not write {path}")
        return path

    def __repr__(self) -> str:
        return f"<rig connected to {self.client.recorder_url}>"


class StatusView(dict):
    """A status dict that prints as the operator's table."""

    def __repr__(self) -> str:
        return format_status(self)


class SummaryView(dict):
    def __repr__(self) -> str:
        return format_summary(self)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="egosurg shell",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--recorder", help="recorder control address")
    parser.add_argument("--config", help="rig.toml, to take the recorder's address from it")
    args = parser.parse_args(argv)
    client = RigClient.connect(args.recorder, args.config)
    namespace: dict[str, Any] = {"rig": Rig(client), "np": np, "cv2": cv2}
    print(BANNER.format(url=client.recorder_url))
    from ptpython.repl import embed

    embed(globals=namespace, locals=namespace, title="EgoSurg rig console")
    return 0
