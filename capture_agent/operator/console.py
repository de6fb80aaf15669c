"""``egosurg shell``: a ptpython console for operators with a connected ``rig``.

Example::

    egosurg shell --config /etc/egosurg/rig.toml
    >>> rig.status()                       # the same table as 'egosurg status'
    >>> rig.start("case-0042", surgeon="A. Smith")
    recording case case-0042 from 4 cameras to /data/egosurg/sessions/case-0042_....h5
    >>> img = rig.last_frame(41234567)     # a BGR numpy image from the live stream
    >>> rig.save_frame(41234567, "check.png")
    >>> rig.stop()                         # the same summary as 'egosurg record stop'
    >>> help(rig)                          # every command, with what it does

Every ``rig`` command answers with an object that the console shows as the CLI's text. A command
the rig refuses (a camera not streaming, nothing to stop, no recorder answering) answers with a
``Refused`` whose display is the one-line reason, e.g. ``rig.start: refused: camera(s) not
streaming: ...``, and which is false in an ``if``. Why not an exception: at a console an operator
reads answers, and a traceback for "not recording; nothing to stop" reads like a crash of the
rig; the reason is what they need, in the words the CLI uses. Scripts that want exceptions use
``capture_agent.operator.rig_client.RigClient``, which raises ``CommandRefusedError``.
Mistakes in the Python itself (a misspelt method, a wrong argument) still show Python's own error.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from capture_agent.errors import ConsoleError
from capture_agent.operator.control import format_started, format_status, format_summary
from capture_agent.operator.rig_client import RigClient
from protocol.command import command_parser
from protocol.errors import UserError
from protocol.private_files import make_owner_only, plaintext_notice

BANNER = """EgoSurg operator console. The object 'rig' is connected to {url}:
  rig.status()                      health of every camera, PTP and disk
  rig.start("case-name", key=value) start recording a case (metadata as keywords)
  rig.stop()                        stop and print the session summary
  rig.last_frame(serial)            the camera's latest image (BGR numpy array)
  rig.save_frame(serial, "f.png")   save it as a picture
  help(rig)                         what each command does
"""


class Refused:
    """A command the rig did not carry out; shown as its one-line reason. False in an ``if``."""

    def __init__(self, command: str, reason: str) -> None:
        self.command = command
        self.reason = reason

    def __bool__(self) -> bool:
        return False

    def __repr__(self) -> str:
        return f"rig.{self.command}: refused: {self.reason}"


class Started(dict):
    """The answer to ``rig.start``: the recorder's result, shown in 'egosurg record start' words."""

    def __repr__(self) -> str:
        return format_started(self)


class StatusView(dict):
    """A status dict that shows as the 'egosurg status' table."""

    def __repr__(self) -> str:
        return format_status(self)


class SummaryView(dict):
    """A stop summary that shows as 'egosurg record stop' prints it."""

    def __repr__(self) -> str:
        return format_summary(self)


class Rig:
    """The rig, as the console's ``rig``: start, stop and watch recordings.

    Each command answers with what 'egosurg record' and 'egosurg status' print; a refused
    command answers with its reason (a ``Refused``, false in an ``if``), never a traceback.
    """

    def __init__(self, client: RigClient) -> None:
        self.client = client

    def status(self) -> StatusView | Refused:
        """Health of every camera (streaming, fps, drops, PTP offset), the agents and the disk,
        and the recording if one runs: the 'egosurg status' table.

        Example: ``rig.status()``; ``rig.status()["cameras"]`` is the raw list.
        """
        return self._ask("status", lambda: StatusView(self.client.status()))

    def start(
        self, case: str, planned_duration_min: float | None = None, **meta: str
    ) -> Started | Refused:
        """Start recording ``case`` from every camera of the rig.

        ``case``: the case name (letters, digits, - _ .), the start of the session file's name.
        ``planned_duration_min``: minutes the disk must hold (default: rig.toml's).
        Keywords are the case's metadata, e.g. ``rig.start("case-0042", surgeon="A. Smith")``.
        Refused, with the reason, when a camera is not streaming, PTP is not locked, the disk
        is too small or a recording already runs.
        """
        return self._ask(
            "start", lambda: Started(self.client.start(case, planned_duration_min, **meta))
        )

    def stop(self) -> SummaryView | Refused:
        """Stop the recording and show its summary: frames, drops and gaps per camera, and the
        file (the 'egosurg record stop' table). Refused when nothing is recording."""
        return self._ask("stop", lambda: SummaryView(self.client.stop()))

    def last_frame(self, camera: int, side: str = "left") -> np.ndarray | Refused:
        """The next image of ``camera`` (its serial) from its agent's live stream, as a BGR
        numpy array (height, width, 3); ``side`` is "left" or "right"."""
        return self._ask("last_frame", lambda: self.client.last_frame(camera, side))

    def save_frame(self, camera: int, path: str, side: str = "left") -> str | Refused:
        """Save the next image of ``camera`` as a picture at ``path`` (.png or .jpg); answers
        the path. ``side`` is "left" or "right"."""

        def save() -> str:
            image = self.client.last_frame(camera, side)
            if not cv2.imwrite(path, image):
                raise ConsoleError(f"could not write {path}; check the folder and the extension")
            make_owner_only(Path(path))  # a live picture of the room: whatever the shell's umask
            print(plaintext_notice("a live frame", path), file=sys.stderr)
            return path

        return self._ask("save_frame", save)

    def _ask(self, command: str, do: Any) -> Any:
        try:
            return do()
        except UserError as exc:
            return Refused(command, str(exc))

    def __repr__(self) -> str:
        return f"<rig connected to {self.client.recorder_url}; help(rig) lists its commands>"


def namespace(client: RigClient) -> dict[str, Any]:
    """What the console starts with: ``rig``, ``np`` and ``cv2``."""
    return {"rig": Rig(client), "np": np, "cv2": cv2}


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg shell", __doc__)
    parser.add_argument("--recorder", help="recorder control address")
    parser.add_argument("--config", help="rig.toml, to take the recorder's address from it")
    args = parser.parse_args(argv)
    client = RigClient.connect(args.recorder, args.config)
    names = namespace(client)
    print(BANNER.format(url=client.recorder_url))
    from ptpython.repl import embed

    embed(globals=names, locals=names, title="EgoSurg rig console")
    return 0
