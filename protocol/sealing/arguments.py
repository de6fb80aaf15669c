"""``--identity FILE``: how every command that reads sessions is given the key that opens a
sealed one, the same way everywhere (``egosurg session``, ``calibrate``, ``reconstruct``,
``evaluate``, ``replay --pip``).

The option names a recipient's ``.identity`` file; without it the file named by
``$EGOSURG_IDENTITY`` is used. Nothing is loaded when neither is given: a plaintext session needs
no identity, and the session reader refuses a sealed one in one line naming its recipients.

Example::

    parser = command_parser("egosurg session", __doc__)
    add_identity_argument(parser)
    args = parser.parse_args(argv)
    reader = SessionReader(args.file, identity=identity_from_args(args))
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from pathlib import Path

from protocol.sealing.keyfiles import IDENTITY_ENV, Identity, load_identity


def add_identity_argument(parser: argparse.ArgumentParser) -> None:
    """``--identity FILE``: the secret key that opens sealed sessions (else
    ``$EGOSURG_IDENTITY``)."""
    parser.add_argument(
        "--identity",
        type=Path,
        metavar="FILE",
        help=(
            "the .identity file of one of a sealed session's recipients (default: "
            f"${IDENTITY_ENV}); a plaintext session needs none"
        ),
    )


def identity_from_args(
    args: argparse.Namespace, *, needed: bool = True, environ: Mapping[str, str] = os.environ
) -> Identity | None:
    """The identity ``--identity FILE`` or ``$EGOSURG_IDENTITY`` names, loaded and checked
    (``load_identity``: one-line errors for a missing, unreadable, exposed or damaged file).
    ``None`` when neither is given (the session reader then says which recipients' identity a
    sealed session needs; a plaintext one needs none), or when the command will not read a
    session this time (not ``needed``)."""
    path = getattr(args, "identity", None)
    if not needed or (path is None and not environ.get(IDENTITY_ENV)):
        return None
    return load_identity(path, environ)
