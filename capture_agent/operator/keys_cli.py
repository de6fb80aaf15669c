"""``egosurg keys``: make and inspect the CURVE keys of the rig's links.

Every process of the rig (the recorder, each agent, each operator) has one keypair. ``generate``
writes ``NAME.key`` (the public key: copy it to whoever must let this process in) and
``NAME.key_secret`` (the secret key: owner-only, mode 0600, in a folder of mode 0700 if it makes
the folder; it never leaves the machine and is never stored in a session). It refuses to overwrite
an existing key. Name the files in ``node.toml`` / ``rig.toml`` ``[security]`` (docs/capture.md).
``--owner USER`` (run as root) hands the two files, and the folder if it makes it, to the user the
service runs as, so ``User=egosurg`` can read the secret key that ``sudo`` wrote.

Examples::

    sudo egosurg keys generate --owner egosurg --out /etc/egosurg/keys --name orin-a
    egosurg keys generate --out /etc/egosurg/keys --name recorder
    egosurg keys generate --out ~/.egosurg --name operator
    egosurg keys show /etc/egosurg/keys/recorder.key
"""

from __future__ import annotations

import os
import pwd
import re
import stat
from pathlib import Path

import zmq.auth

from capture_agent.errors import KeyFileError
from capture_agent.security import check_secret_mode, load_keypair, load_public_key
from protocol.command import add_subcommand, command_parser
from protocol.errors import UserError
from protocol.formats.security_config import PUBLIC_SUFFIX, SECRET_SUFFIX

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")


def _owner_ids(owner: str) -> tuple[int, int]:
    """(uid, gid) of the user named ``owner``; checked before any file is written."""
    try:
        entry = pwd.getpwnam(owner)
    except KeyError:
        raise UserError(
            f"--owner {owner!r}: no such user on this machine; create the service user first "
            "(docs/capture.md) or name an existing one"
        ) from None
    if os.geteuid() != 0 and entry.pw_uid != os.geteuid():
        raise UserError(f"--owner {owner}: only root may give files to another user; use sudo")
    return entry.pw_uid, entry.pw_gid


def generate(out: Path, name: str, owner: str | None = None) -> tuple[Path, Path]:
    """Write ``out/name.key`` and ``out/name.key_secret``; (public, secret) paths.

    ``owner``: the user who will own both files (and ``out`` if it is made here), e.g. the
    service user ``egosurg``; None leaves them to the user running this.
    """
    if not _NAME.match(name):
        raise KeyFileError(f"key name {name!r}: use letters, digits, - _ . (up to 32 characters)")
    ids = _owner_ids(owner) if owner is not None else None
    out = out.expanduser()
    public, secret = out / f"{name}{PUBLIC_SUFFIX}", out / f"{name}{SECRET_SUFFIX}"
    for p in (public, secret):
        if p.exists():
            raise KeyFileError(
                f"{p} exists; keys are never overwritten (every allow-list that holds the old "
                "public key would lock this process out). Remove it first or pick another --name"
            )
    made_folder = not out.exists()
    if made_folder:
        out.mkdir(mode=0o700, parents=True)
        out.chmod(0o700)  # mkdir's mode is filtered by the umask
    old = os.umask(0o077)  # the secret file is never readable by others, not even for a moment
    try:
        made_public, made_secret = zmq.auth.create_certificates(out, name)
    finally:
        os.umask(old)
    Path(made_secret).chmod(0o600)
    Path(made_public).chmod(0o644)  # a public key is meant to be copied and read
    if ids is not None:
        for p in (Path(made_secret), Path(made_public), *((out,) if made_folder else ())):
            os.chown(p, *ids)
    return Path(made_public), Path(made_secret)


def show(path: Path) -> str:
    """What a key file holds (never the secret itself)."""
    public = load_public_key(path)
    lines = [f"file: {path}", f"public key: {public.decode()}"]
    _, secret = zmq.auth.load_certificate(path)
    if secret is None:
        lines.append("secret key: none (a public key file: copy it into allow-lists)")
    else:
        load_keypair(path)  # checks mode 0600 and that the pair belongs together
        check_secret_mode(path)
        mode = stat.S_IMODE(path.stat().st_mode)
        lines.append(f"secret key: present, mode {mode:04o} (keep it on this machine)")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg keys", __doc__)
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_subcommand(sub, "generate", "make a keypair (NAME.key and NAME.key_secret)")
    p.add_argument("--out", type=Path, required=True, help="folder for the two files")
    p.add_argument("--name", required=True, help="the process: recorder, orin-a, operator, ...")
    p.add_argument(
        "--owner", help="user to own the files (the service's user, e.g. egosurg; needs root)"
    )
    p = add_subcommand(sub, "show", "print the public key of a .key or .key_secret file")
    p.add_argument("file", type=Path)
    args = parser.parse_args(argv)
    if args.action == "generate":
        public, secret = generate(args.out, args.name, args.owner)
        owned = f", owned by {args.owner}" if args.owner else ""
        print(
            f"public key (share it): {public}\n"
            f"secret key (mode 0600{owned}, keep it here): {secret}"
        )
    else:
        print(show(args.file))
    return 0
