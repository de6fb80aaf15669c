"""The one ``egosurg`` command.

Each subcommand lives in its own module with a ``main(argv) -> int``. This dispatcher names those
modules only as strings and imports one only when its subcommand runs, so ``egosurg agent`` on a
small edge node never loads torch or open3d, and protocol/ keeps importing none of the other
packages at import time.

Example::

    egosurg sim frames --out frames/ --t-start 0 --t-end 1
"""

from __future__ import annotations

import importlib
import logging
import sys
from collections.abc import Sequence

from protocol.errors import UserError
from protocol.private_files import owner_only_umask

# name -> ("module:function", one-line summary). Order is the order shown in --help.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("sim.demo:main", "run the whole chain on the simulated rig and write pictures"),
    "agent": ("capture_agent.agent.agent:main", "the capture daemon of one Jetson node"),
    "recorder": (
        "capture_agent.recorder.recorder:main",
        "the recorder: sync all agents, write sessions",
    ),
    "record": ("capture_agent.operator.control:main_record", "start or stop recording a case"),
    "status": (
        "capture_agent.operator.control:main_status",
        "the rig's health: fps, drops, PTP, disk",
    ),
    "shell": ("capture_agent.operator.console:main", "an operator console with a connected 'rig'"),
    "keys": (
        "capture_agent.operator.keys_cli:main",
        "make the CURVE keys that secure the rig's links",
    ),
    "session": (
        "capture_agent.operator.session_cli:main",
        "inspect, verify and export a session file",
    ),
    "calibrate": ("calibration.cli:main", "extrinsic calibration of the rig from a wand session"),
    "reconstruct": (
        "reconstructor.cli:main_reconstruct",
        "3D Gaussian splats of chosen timestamps of a session",
    ),
    "case": ("reconstructor.case.cli:main", "a batch-reconstructed case: info, export"),
    "render": ("reconstructor.cli:main_render", "render a splat model from any viewpoint"),
    "replay": ("reconstructor.replay.cli:main_replay", "a case from a path or a role, to MP4"),
    "sightline": (
        "reconstructor.replay.cli:main_sightline",
        "a target's visible fraction from a viewer over a case, and from a moved position",
    ),
    "sterile": (
        "reconstructor.replay.cli:main_sterile",
        "moving things entering a sterile field box over a case: events, renders",
    ),
    "view": ("reconstructor.replay.cli:main_view", "browse a case in a web browser (localhost)"),
    "people": (
        "reconstructor.people.cli:main",
        "who stood where and looked where: people tracked from a case, tracks named as roles",
    ),
    "report": (
        "reconstructor.report.cli:main",
        "one self-contained HTML report of a case: health, timeline, events, views",
    ),
    "evaluate": (
        "reconstructor.evaluation.cli:main",
        "the paper's evaluation protocols and baselines on an evaluation set",
    ),
    "sim": ("sim.cli:main", "the simulated operating room: frames, factory files, views"),
}


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    rows = "\n".join(f"  {n.ljust(width)}  {summary}" for n, (_, summary) in COMMANDS.items())
    return (
        "usage: egosurg [-v] <command> [options]\n\n"
        "Turn an operating room's wall-mounted stereo cameras into a navigable 3D record.\n\n"
        f"commands:\n{rows}\n\n"
        "Run 'egosurg <command> --help' for a command's options and an example."
    )


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    level = logging.INFO
    while args and args[0] in ("-v", "--verbose", "-q", "--quiet"):
        level = logging.DEBUG if args.pop(0) in ("-v", "--verbose") else logging.WARNING
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args or args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(f"egosurg: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, _, func_name = COMMANDS[name][0].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        print(
            f"egosurg {name}: cannot load {module_name}: {exc}. Install the full product with "
            "\"pip install 'egosurg[workstation]'\" (a node's edge install, plain "
            "'pip install egosurg', lacks this command).",
            file=sys.stderr,
        )
        return 2
    try:
        # Nearly everything a command writes shows a patient or names a case (models, PLYs,
        # renders, MP4s, frames, logs): owner-only from creation on, whatever the shell's umask,
        # rather than a mode passed by every writer and library (protocol/private_files.py).
        with owner_only_umask():
            return int(getattr(module, func_name)(rest) or 0)
    except UserError as exc:
        print(f"egosurg {name}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"egosurg {name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
