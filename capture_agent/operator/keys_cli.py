"""``egosurg keys``: make and inspect the rig's keys: the CURVE keys of its links, and the site
keys that sessions are sealed for.

``--kind link`` (the default): every process of the rig (the recorder, each agent, each
operator) has one keypair. ``generate`` writes ``NAME.key`` (the public key: copy it to whoever
must let this process in) and ``NAME.key_secret`` (the secret key: owner-only, mode 0600, in a
folder of mode 0700 if it makes the folder; it never leaves the machine and is never stored in a
session). It refuses to overwrite an existing key. Name the files in ``node.toml`` /
``rig.toml`` ``[security]`` (docs/capture.md). ``--owner USER`` (run as root) hands the two
files, and the folder if it makes it, to the user the service runs as, so ``User=egosurg`` can
read the secret key that ``sudo`` wrote.

``--kind site``: a recipient keypair for sealed sessions (``protocol.sealing``).
``NAME.recipient`` is the public key (give it to every recorder that seals for this site);
``NAME.identity`` is the secret key that opens those sessions (mode 0600 in a 0700 folder,
never overwritten): keep it on the machines that read sessions, never on the recorder. Keep two
recipients, one offline: losing every identity a session was sealed for loses the session.
``identity`` checks the identity that readers would use (``--identity FILE``, else
``$EGOSURG_IDENTITY``) and prints its public half.

Examples::

    sudo egosurg keys generate --owner egosurg --out /etc/egosurg/keys --name orin-a
    egosurg keys generate --out /etc/egosurg/keys --name recorder
    egosurg keys generate --out ~/.egosurg --name operator
    egosurg keys show /etc/egosurg/keys/recorder.key
    egosurg keys generate --kind site --out ~/.egosurg/site --name hospital-a
    egosurg keys identity --identity ~/.egosurg/site/hospital-a.identity
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
from protocol.sealing import (
    IDENTITY_SUFFIX,
    KINDS,
    RECIPIENT_SUFFIX,
    generate_identity,
    load_identity,
    load_recipient,
    write_identity,
)

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")
KEY_KINDS = ("link", *KINDS)


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


def generate(
    out: Path, name: str, owner: str | None = None, kind: str = "link"
) -> tuple[Path, Path]:
    """Write a keypair into ``out``; (public, secret) paths. ``kind`` ``link``: ``name.key`` and
    ``name.key_secret`` (CURVE); ``site``: ``name.recipient`` and ``name.identity`` (X25519).

    ``owner``: the user who will own both files (and ``out`` if it is made here), e.g. the
    service user ``egosurg``; None leaves them to the user running this.
    """
    if kind not in KEY_KINDS:
        raise KeyFileError(f"--kind {kind!r}: use one of {', '.join(KEY_KINDS)}")
    if not _NAME.match(name):
        raise KeyFileError(f"key name {name!r}: use letters, digits, - _ . (up to 32 characters)")
    ids = _owner_ids(owner) if owner is not None else None
    out = out.expanduser()
    made_folder = not out.exists()
    if kind == "link":
        made_public, made_secret = _generate_link(out, name)
    else:
        made_public, made_secret = write_identity(generate_identity(name, kind), out)
    if ids is not None:
        for p in (made_secret, made_public, *((out,) if made_folder else ())):
            os.chown(p, *ids)
    return made_public, made_secret


def _generate_link(out: Path, name: str) -> tuple[Path, Path]:
    public, secret = out / f"{name}{PUBLIC_SUFFIX}", out / f"{name}{SECRET_SUFFIX}"
    for p in (public, secret):
        if p.exists():
            raise KeyFileError(
                f"{p} exists; keys are never overwritten (every allow-list that holds the old "
                "public key would lock this process out). Remove it first or pick another --name"
            )
    if not out.exists():
        out.mkdir(mode=0o700, parents=True)
        out.chmod(0o700)  # mkdir's mode is filtered by the umask
    old = os.umask(0o077)  # the secret file is never readable by others, not even for a moment
    try:
        made_public, made_secret = zmq.auth.create_certificates(out, name)
    finally:
        os.umask(old)
    Path(made_secret).chmod(0o600)
    Path(made_public).chmod(0o644)  # a public key is meant to be copied and read
    return Path(made_public), Path(made_secret)


def show(path: Path) -> str:
    """What a key file holds (never the secret itself)."""
    if path.suffix in (RECIPIENT_SUFFIX, IDENTITY_SUFFIX):
        return _show_site(path, identity=path.suffix == IDENTITY_SUFFIX)
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


def _show_site(path: Path | None, *, identity: bool) -> str:
    """A site key file: its recipient, and for an identity file (None: ``$EGOSURG_IDENTITY``)
    that it loads: mode 0600, its two halves belonging together."""
    if identity:
        loaded = load_identity(path)
        recipient, file = loaded.recipient, loaded.path or Path()
    else:
        file = path or Path()
        recipient = load_recipient(file)
    lines = [f"file: {file}", f"recipient: {recipient.label()}", f"kind: {recipient.kind}"]
    if identity:
        mode = stat.S_IMODE(file.stat().st_mode)
        lines.append(f"secret key: present, mode {mode:04o} (keep it where sessions are read)")
        lines.append(f"public half, as a {RECIPIENT_SUFFIX} file:\n{recipient.text().rstrip()}")
    else:
        lines.append("secret key: none (name this file as a recipient in rig.toml)")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg keys", __doc__)
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_subcommand(
        sub,
        "generate",
        "make a keypair (link: NAME.key + NAME.key_secret; site: NAME.recipient + NAME.identity)",
    )
    p.add_argument("--out", type=Path, required=True, help="folder for the two files")
    p.add_argument("--name", required=True, help="the process: recorder, orin-a, operator, ...")
    p.add_argument(
        "--owner", help="user to own the files (the service's user, e.g. egosurg; needs root)"
    )
    p.add_argument(
        "--kind",
        default="link",
        choices=KEY_KINDS,
        help="link: CURVE keys of the rig's links (default); site: a recipient of sealed sessions",
    )
    p = add_subcommand(sub, "show", "print the public key of a key, recipient or identity file")
    p.add_argument("file", type=Path)
    p = add_subcommand(sub, "identity", "check the identity readers use and print its recipient")
    p.add_argument("--identity", type=Path, help=f"the {IDENTITY_SUFFIX} file ($EGOSURG_IDENTITY)")
    args = parser.parse_args(argv)
    if args.action == "identity":
        print(_show_site(args.identity, identity=True))
        return 0
    if args.action == "generate":
        public, secret = generate(args.out, args.name, args.owner, args.kind)
        owned = f", owned by {args.owner}" if args.owner else ""
        print(
            f"public key (share it): {public}\n"
            f"secret key (mode 0600{owned}, keep it here): {secret}"
        )
    else:
        print(show(args.file))
    return 0
