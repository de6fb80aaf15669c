"""One way to write an ``egosurg`` command: its parser, its subcommands and its argument error.

A command module builds its parser with :func:`command_parser`, whose ``--help`` shows the module
docstring verbatim (it carries the runnable example), and registers each subcommand
with :func:`add_subcommand` and its one-line summary. A usage mistake (a missing or unknown
option, a bad choice or number) raises :class:`CommandArgumentError` instead of argparse's usage
dump and ``SystemExit``: the ``egosurg`` dispatcher prints any ``UserError`` as one line and exits
with code 2, so a user mistake found by argparse and one found by the command's own checks read
the same. :func:`parse_size_px` reads a ``WxH`` option the same way in every command. This module
needs only the standard library: the edge's commands use it. (A command that reads sessions takes
``--identity FILE`` through ``protocol/sealing/arguments.py``.)

Example::

    parser = command_parser("egosurg keys", __doc__)
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_subcommand(sub, "show", "print the public key of a .key or .key_secret file")
    p.add_argument("file")
    args = parser.parse_args(argv)
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import NoReturn

from protocol.errors import UserError


class CommandArgumentError(UserError, ValueError):
    """A command-line argument that cannot be used; the message names the option and the value."""


class CommandParser(argparse.ArgumentParser):
    """argparse whose usage errors are a :class:`CommandArgumentError` (one line, exit 2)."""

    def error(self, message: str) -> NoReturn:
        raise CommandArgumentError(f"{message} (see '{self.prog} --help')")


def command_parser(prog: str, doc: str | None) -> CommandParser:
    """The parser of command ``prog`` (e.g. ``"egosurg session"``), its help text ``doc`` as
    written: the module docstring keeps its example's line breaks."""
    return CommandParser(
        prog=prog, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )


def add_subcommand(
    sub: argparse._SubParsersAction,
    name: str,
    summary: str,
    func: Callable[[argparse.Namespace], int] | None = None,
) -> argparse.ArgumentParser:
    """Register subcommand ``name`` with its one-line ``summary`` (the parent's ``--help`` lists
    it); ``func`` runs it (``args.func(args)``). The subparser is a :class:`CommandParser` too,
    since argparse makes subparsers of the parent's class."""
    p = sub.add_parser(name, help=summary)
    # A missing subcommand is then reported by its choices ("required: {info,verify}"), not by
    # the namespace field it fills; --help prints the same braces either way.
    sub.metavar = "{" + ",".join(sub.choices or ()) + "}"
    if func is not None:
        p.set_defaults(func=func)
    return p


def parse_size_px(
    text: str, option: str, *, min_px: int = 16, max_px: int | None = 8192, even: bool = False
) -> tuple[int, int]:
    """``"960x600"`` -> ``(960, 600)``, the (width, height) in pixels an option such as
    ``--size`` names; ``even``: both sides even (a video encoder's 4:2:0 chroma needs it)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CommandArgumentError(f"{option} {text!r}: write it as WxH, e.g. 960x600") from None
    top = max_px if max_px is not None else max(w, h, min_px)
    if not (min_px <= w <= top and min_px <= h <= top) or (even and (w % 2 or h % 2)):
        sides = f"{min_px} to {max_px} px" if max_px is not None else f"at least {min_px} px"
        raise CommandArgumentError(
            f"{option} {text!r}: {'even ' if even else ''}sides of {sides}, e.g. 960x600"
        )
    return w, h
