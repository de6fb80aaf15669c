"""Recipient keypairs: X25519 keys in two small text files, written and read strictly.

``NAME.recipient`` (the public key, mode 0644: copy it to every recorder that must seal for
it) and ``NAME.identity`` (the secret key, mode 0600 in a 0700 folder; it opens every session
sealed for the recipient, so it lives only where sessions are read). Both are UTF-8 text: lines
starting with ``#`` are comments, the first other line is the header, then one ``field: value``
line per field, each field exactly once, in any order::

    egosurg-identity v1            (egosurg-recipient v1 in the public file)
    kind: site
    name: hospital-a
    key-id: 5f0c1a7e93b24d18
    public: <standard base64 of the 32-byte X25519 public key>
    secret: <standard base64 of the 32-byte X25519 secret key>   (identity file only)

``key-id`` is the first 8 bytes, as 16 lower-case hex digits, of
SHA-256(``b"egosurg-recipient v1"`` + public key); a reader recomputes it, and recomputes the
public key from the secret one, and refuses a file where either differs.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import os
import re
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey

from protocol.sealing.errors import IdentityError

IDENTITY_HEADER = "egosurg-identity v1"
RECIPIENT_HEADER = "egosurg-recipient v1"
IDENTITY_SUFFIX = ".identity"
RECIPIENT_SUFFIX = ".recipient"
IDENTITY_ENV = "EGOSURG_IDENTITY"
KINDS = ("site",)  # a recipient that opens a site's sessions; escrow keys are site keys too
KEY_BYTES = 32
KEY_ID_BYTES = 8
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")


def key_id_of(public: bytes) -> bytes:
    """The 8-byte key id of an X25519 public key (stored beside each wrap of a data key)."""
    return hashlib.sha256(RECIPIENT_HEADER.encode() + public).digest()[:KEY_ID_BYTES]


def check_name(name: str) -> str:
    if not _NAME.match(name):
        raise IdentityError(f"key name {name!r}: use letters, digits, - _ . (up to 32 characters)")
    return name


@dataclass(frozen=True, kw_only=True)
class Recipient:
    """A public key that sessions are sealed for. ``name`` is a label for messages only: the
    key id, derived from the key, is what a reader matches."""

    name: str
    kind: str
    public: bytes

    def __post_init__(self) -> None:
        check_name(self.name)
        if self.kind not in KINDS or len(self.public) != KEY_BYTES:
            raise ValueError(f"a recipient is a {KEY_BYTES}-byte key of kind {', '.join(KINDS)}")

    @property
    def key_id(self) -> bytes:
        return key_id_of(self.public)

    def label(self) -> str:
        return f"{self.name} (key id {self.key_id.hex()})"

    def text(self) -> str:
        return _render(RECIPIENT_HEADER, self, secret=None)


@dataclass(frozen=True, kw_only=True, repr=False)
class Identity:
    """A recipient's secret key; ``repr`` never shows the secret."""

    recipient: Recipient
    secret: bytes
    path: Path | None = None

    def __repr__(self) -> str:
        return f"Identity({self.recipient.label()})"

    def text(self) -> str:
        return _render(IDENTITY_HEADER, self.recipient, secret=self.secret)


def generate_identity(name: str, kind: str = "site") -> Identity:
    if kind not in KINDS:
        raise IdentityError(f"key kind {kind!r}: use one of {', '.join(KINDS)}")
    secret_key = X25519PrivateKey.generate()
    public = secret_key.public_key().public_bytes_raw()
    recipient = Recipient(name=check_name(name), kind=kind, public=public)
    return Identity(recipient=recipient, secret=secret_key.private_bytes_raw())


def _render(header: str, recipient: Recipient, *, secret: bytes | None) -> str:
    what = (
        "identity: the SECRET key that opens every session sealed for it. Keep it mode 0600, "
        "never on a recorder"
        if secret
        else "recipient: the public key. Name it in rig.toml to seal sessions for it"
    )
    lines = [
        f"# egosurg {recipient.kind} {recipient.name} {what}",
        header,
        f"kind: {recipient.kind}",
        f"name: {recipient.name}",
        f"key-id: {recipient.key_id.hex()}",
        f"public: {base64.b64encode(recipient.public).decode()}",
    ]
    if secret is not None:
        lines.append(f"secret: {base64.b64encode(secret).decode()}")
    return "\n".join(lines) + "\n"


def write_identity(identity: Identity, out: Path) -> tuple[Path, Path]:
    """Write ``out/NAME.recipient`` (0644) and ``out/NAME.identity`` (0600, made with
    ``O_EXCL``: an existing key is never overwritten); ``out`` is made 0700 if missing.
    Returns (recipient path, identity path)."""
    name = identity.recipient.name
    public, secret = out / f"{name}{RECIPIENT_SUFFIX}", out / f"{name}{IDENTITY_SUFFIX}"
    for p in (public, secret):
        if p.exists():
            raise IdentityError(
                f"{p} exists; keys are never overwritten (sessions sealed for the old key need "
                "it to open). Move it away first or pick another --name"
            )
    if not out.exists():
        out.mkdir(mode=0o700, parents=True)
        out.chmod(0o700)  # mkdir's mode is filtered by the umask
    _write_new(secret, identity.text(), 0o600)
    try:
        _write_new(public, identity.recipient.text(), 0o644)
    except BaseException:
        secret.unlink()
        raise
    return public, secret


def _write_new(path: Path, text: str, mode: int) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.fchmod(fd, mode)  # the umask may have taken bits a public file should have
        os.write(fd, text.encode())
        os.fsync(fd)
    finally:
        os.close(fd)


def load_recipient(path: Path) -> Recipient:
    """A ``.recipient`` file (or the public half of an ``.identity`` file)."""
    fields = _parse(path, _read_text(path, "recipient file"), (RECIPIENT_HEADER, IDENTITY_HEADER))
    return _recipient(path, fields)


def load_identity(path: Path | None, environ: Mapping[str, str] = os.environ) -> Identity:
    """The identity named by ``path`` (``--identity FILE``), else by ``$EGOSURG_IDENTITY``.

    Refused, in one line each: none given, missing, unreadable, readable or writable by group
    or others, not an identity file (a recipient file, another format), a damaged field.
    """
    if path is None:
        value = environ.get(IDENTITY_ENV, "")
        if not value:
            raise IdentityError(
                f"no identity given: pass --identity FILE or set {IDENTITY_ENV} to the "
                f"{IDENTITY_SUFFIX} file of one of the session's recipients"
            )
        path = Path(value)
    path = path.expanduser()
    fields = _parse(path, _read_text(path, "identity file"), (IDENTITY_HEADER,))
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise IdentityError(
            f"identity file {path} has mode {mode:04o}: group or others may use it. Run "
            f"'chmod 600 {path}' if only you have had access, else treat the key as exposed"
        )
    recipient = _recipient(path, fields)
    secret = _key(path, fields, "secret")
    derived = X25519PrivateKey.from_private_bytes(secret).public_key().public_bytes_raw()
    if derived != recipient.public:
        raise IdentityError(f"identity file {path}: its public key does not belong to its secret")
    return Identity(recipient=recipient, secret=secret, path=path)


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        raise IdentityError(f"{what} {path} does not exist; check the path") from None
    except PermissionError:
        raise IdentityError(
            f"{what} {path} cannot be read by this user; run as its owner or fix its owner"
        ) from None
    except IsADirectoryError:
        raise IdentityError(f"{what} {path} is a folder; name the file inside it") from None
    except UnicodeDecodeError:
        raise IdentityError(f"{what} {path} is not a text key file") from None
    except OSError as exc:
        raise IdentityError(f"{what} {path} cannot be read: {exc.strerror}") from None


def _parse(path: Path, text: str, headers: tuple[str, ...]) -> dict[str, str]:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines or lines[0] not in headers:
        first = lines[0][:40] if lines else "nothing"
        want = " or ".join(repr(h) for h in headers)
        raise IdentityError(f"{path}: starts with {first!r}, not {want}; is it the right file?")
    fields: dict[str, str] = {}
    for line in lines[1:]:
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or key in fields:
            problem = "a repeated field" if sep else "not 'field: value'"
            raise IdentityError(f"{path}: line {line[:40]!r} is {problem}")
        fields[key] = value.strip()
    wanted = {"kind", "name", "key-id", "public"} | (
        {"secret"} if lines[0] == IDENTITY_HEADER else set()
    )
    if set(fields) != wanted:
        raise IdentityError(f"{path}: fields {sorted(fields)}, expected {sorted(wanted)}")
    return fields


def _key(path: Path, fields: dict[str, str], field: str) -> bytes:
    try:
        raw = base64.b64decode(fields[field], validate=True)
    except binascii.Error:
        raw = b""
    if len(raw) != KEY_BYTES:
        raise IdentityError(f"{path}: its {field} key is not {KEY_BYTES} bytes of base64")
    return raw


def _recipient(path: Path, fields: dict[str, str]) -> Recipient:
    if fields["kind"] not in KINDS:
        raise IdentityError(f"{path}: kind {fields['kind']!r} is not one of {', '.join(KINDS)}")
    try:
        name = check_name(fields["name"])
    except IdentityError as exc:
        raise IdentityError(f"{path}: {exc}") from None
    public = _key(path, fields, "public")
    X25519PublicKey.from_public_bytes(public)
    recipient = Recipient(name=name, kind=fields["kind"], public=public)
    if fields["key-id"] != recipient.key_id.hex():
        raise IdentityError(f"{path}: key-id {fields['key-id'][:20]!r} is not its public key's")
    return recipient
