"""Sealed derived files: data made from a sealed session (a case's models, its cached depth),
sealed for the same recipients as the session itself.

Each file has its own fresh data key, wrapped for the session's recipients in a key block that
carries the *session's* uid (so the key is bound to the session, and so is every payload), and
one sealed payload whose associated data names what the file is (its role) and which timestamp
or entry it is (its name). A model copied to another timestamp, or into the case of another
session, does not open, and the error names it. A checksum over every byte before it ends the
file, so its integrity is checked without a key (``check_sealed_file``; ``egosurg case info
--verify`` checks the index's checksum over the same bytes).

File format (integers little-endian; ``||`` joins bytes; the key block and the sealed payload
are exactly those of ``protocol.sealing``'s docstring):

=======  ==========  ===========================================================
offset   bytes       content
=======  ==========  ===========================================================
0        4           magic ``b"EGSD"``
4        1           version, 1
5        1           role: 1 a case model, 2 a cached depth stage
6        2           K, the length of the key block (u16)
8        K           key block (``EGSK`` v1): the session's uid, this file's data key
                     wrapped for each of the session's recipients
8+K      P           sealed payload: version || nonce || ciphertext || tag
8+K+P    8           xxh3-64 of bytes 0 to 8+K+P (u64)
=======  ==========  ===========================================================

The payload's associated data is a sealed payload's (``EGSP`` ...) with the field
``<role>/<name>`` (``model/t00012.000``: the timestamp the model is of; ``depth/<key>``: the
depth entry's 32-hex-digit key, its file name) and camera serial 0, row 0, side 2 (none),
capture stamp 0. What the plaintext is (the ``.npz`` a plaintext case stores) is the role's.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import xxhash

from protocol.sealing.errors import (
    IdentityRequiredError,
    KeyBlockError,
    SealedPayloadError,
)
from protocol.sealing.keyfiles import IDENTITY_ENV, Identity, Recipient
from protocol.sealing.payload import PayloadContext, Sealer
from protocol.sealing.wrap import (
    SESSION_UID_BYTES,
    KeyBlock,
    new_data_key,
    unwrap_data_key,
    wrap_data_key,
)

MAGIC = b"EGSD"
VERSION = 1
Role = Literal["model", "depth"]
ROLES: dict[str, int] = {"model": 1, "depth": 2}
_HEAD = struct.Struct("<4sBBH")
_SUM = struct.Struct("<Q")
_NAMES = {v: k for k, v in ROLES.items()}


def is_sealed_file(head: bytes | bytearray | memoryview) -> bool:
    """Whether bytes (at least the first 4 of a file) start a sealed derived file."""
    return bytes(head[:4]) == MAGIC


@dataclass(frozen=True)
class _Parts:
    role: str
    block: KeyBlock
    payload: memoryview


def _split(raw: bytes | bytearray | memoryview, where: str) -> _Parts:
    """The parts of a sealed file, after checking its structure and checksum (no key)."""
    view = memoryview(raw)
    if len(view) < _HEAD.size + _SUM.size or not is_sealed_file(view):
        raise SealedPayloadError(
            f"{where} is not a sealed egosurg file (no {MAGIC.decode()} header, or cut short)"
        )
    _magic, version, role, k = _HEAD.unpack_from(view)
    if version != VERSION:
        raise SealedPayloadError(
            f"{where} is sealed in version {version}, not {VERSION}: damaged, or written by a "
            "newer egosurg"
        )
    (stored,) = _SUM.unpack_from(view, len(view) - _SUM.size)
    if xxhash.xxh3_64_intdigest(view[: len(view) - _SUM.size]) != stored:
        raise SealedPayloadError(
            f"{where} fails its checksum (xxh3-64 over its sealed bytes): it is damaged or cut "
            "short"
        )
    if role not in _NAMES or _HEAD.size + k > len(view) - _SUM.size:
        raise SealedPayloadError(f"{where}: role {role} or key block length {k} is not valid")
    try:
        block = KeyBlock.from_bytes(bytes(view[_HEAD.size : _HEAD.size + k]))
    except KeyBlockError as exc:
        raise SealedPayloadError(f"{where}: {exc}") from None
    return _Parts(_NAMES[role], block, view[_HEAD.size + k : len(view) - _SUM.size])


def check_sealed_file(raw: bytes | bytearray | memoryview, where: str) -> str:
    """Checks a sealed file's structure and checksum without a key; returns whom it is sealed
    for (``SealedPayloadError`` naming ``where`` otherwise)."""
    return _split(raw, where).block.recipients()


class DerivedSeal:
    """Seals and opens the derived files of one sealed session: ``session_uid`` (its key
    block's) and ``recipients`` (its stored list) for writing; ``identity``, one recipient's,
    for reading. Holds no data key: each file has its own."""

    def __init__(
        self, session_uid: bytes, recipients: Sequence[Recipient], identity: Identity | None
    ) -> None:
        if len(session_uid) != SESSION_UID_BYTES or not recipients:
            raise ValueError("a derived seal needs the session's 16-byte uid and its recipients")
        self.session_uid = session_uid
        self.recipients = tuple(recipients)
        self.identity = identity

    def describe(self) -> str:
        return ", ".join(r.label() for r in self.recipients)

    def required(self, what: str) -> IdentityRequiredError:
        return IdentityRequiredError(
            f"{what} is sealed for the session's recipients, {self.describe()}: pass "
            f"--identity FILE (one of their identity files) or set {IDENTITY_ENV}"
        )

    def require_identity(self, what: str) -> None:
        if self.identity is None:
            raise self.required(what)

    def seal(self, role: Role, name: str, payload: bytes | bytearray | memoryview) -> bytes:
        """The sealed file's bytes (format in the module docstring)."""
        data_key = new_data_key()
        block = wrap_data_key(data_key, self.recipients, self.session_uid).to_bytes()
        body = Sealer(data_key, self.session_uid).seal(payload, _context(role, name))
        head = _HEAD.pack(MAGIC, VERSION, ROLES[role], len(block))
        out = bytearray(head)
        out += block
        out += body
        out += _SUM.pack(xxhash.xxh3_64_intdigest(out))
        return bytes(out)

    def open(self, role: Role, name: str, raw: bytes | bytearray | memoryview, where: str) -> bytes:
        """The plaintext of a sealed file read at ``where`` as ``role`` ``name``; one-line
        errors: damaged (checksum), another session's, moved from another name or role, no
        identity (naming the recipients) or one that is not a recipient."""
        parts = _split(raw, where)
        if parts.block.session_uid != self.session_uid:
            raise SealedPayloadError(
                f"{where} was sealed for another session (uid {parts.block.session_uid.hex()}, "
                f"this one's is {self.session_uid.hex()}): it was copied here from another "
                "case; rerun the case's reconstruct command to make it again"
            )
        if parts.role != role:
            raise SealedPayloadError(f"{where} is a sealed {parts.role}, not a {role}")
        if self.identity is None:
            raise self.required(where)
        data_key = unwrap_data_key(parts.block, [self.identity])
        try:
            return Sealer(data_key, self.session_uid).open(parts.payload, _context(role, name))
        except SealedPayloadError:
            raise SealedPayloadError(
                f"{where} does not open as {role} {name}: it was moved or copied here from "
                "another timestamp, or changed and its checksum forged; rerun the case's "
                "reconstruct command to make it again"
            ) from None


def _context(role: Role, name: str) -> PayloadContext:
    return PayloadContext(field=f"{role}/{name}")
