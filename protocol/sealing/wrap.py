"""A session's data key, wrapped for each of its recipients: the key block.

The recorder makes a fresh 32-byte data key per session, wraps it for every recipient's public
key and keeps only the key block; it holds no secret that unwraps it, so a stolen recorder
cannot read what it wrote. The byte format is in ``protocol.sealing``'s docstring.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import AESGCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from protocol.sealing.errors import KeyBlockError, WrongIdentityError
from protocol.sealing.keyfiles import KEY_BYTES, KEY_ID_BYTES, Identity, Recipient

KEY_BLOCK_MAGIC = b"EGSK"
KEY_BLOCK_VERSION = 1
SESSION_UID_BYTES = 16
DATA_KEY_BYTES = 32
WRAP_INFO = b"egosurg data key wrap v1"
WRAP_NONCE = bytes(12)  # each wrap key is used once (a fresh ephemeral key per wrap)
WRAPPED_BYTES = DATA_KEY_BYTES + 16  # AES-256-GCM ciphertext and tag
MAX_RECIPIENTS = 16
_HEAD = struct.Struct(f"<4sB{SESSION_UID_BYTES}sB")


@dataclass(frozen=True, kw_only=True)
class Wrap:
    """The data key sealed for one recipient."""

    key_id: bytes
    name: str  # a label for messages; not authenticated: the key id decides
    ephemeral_public: bytes
    wrapped: bytes

    def label(self) -> str:
        return f"{self.name} (key id {self.key_id.hex()})"


@dataclass(frozen=True, kw_only=True)
class KeyBlock:
    """The session's uid and its data key wrapped for each recipient."""

    session_uid: bytes
    wraps: tuple[Wrap, ...]

    def recipients(self) -> str:
        return ", ".join(w.label() for w in self.wraps)

    def to_bytes(self) -> bytes:
        parts = [_HEAD.pack(KEY_BLOCK_MAGIC, KEY_BLOCK_VERSION, self.session_uid, len(self.wraps))]
        for w in self.wraps:
            name = w.name.encode()
            parts += [w.key_id, bytes([len(name)]), name, w.ephemeral_public, w.wrapped]
        return b"".join(parts)

    @classmethod
    def from_bytes(cls, raw: bytes) -> KeyBlock:
        if len(raw) < _HEAD.size:
            raise KeyBlockError(f"the key block is {len(raw)} bytes, shorter than its header")
        magic, version, uid, count = _HEAD.unpack_from(raw)
        if magic != KEY_BLOCK_MAGIC or version != KEY_BLOCK_VERSION:
            raise KeyBlockError(
                f"the key block starts {magic!r} version {version}, not {KEY_BLOCK_MAGIC!r} "
                f"version {KEY_BLOCK_VERSION}; a newer egosurg may read it"
            )
        if not 1 <= count <= MAX_RECIPIENTS:
            raise KeyBlockError(f"the key block names {count} recipients (1 to {MAX_RECIPIENTS})")
        wraps, at = [], _HEAD.size
        for _ in range(count):
            wrap, at = _read_wrap(raw, at)
            wraps.append(wrap)
        if at != len(raw):
            raise KeyBlockError(f"the key block has {len(raw) - at} bytes after its last wrap")
        return cls(session_uid=uid, wraps=tuple(wraps))


def _read_wrap(raw: bytes, at: int) -> tuple[Wrap, int]:
    def take(n: int) -> bytes:
        nonlocal at
        if at + n > len(raw):
            raise KeyBlockError("the key block is truncated inside a recipient's wrap")
        at += n
        return raw[at - n : at]

    key_id = take(KEY_ID_BYTES)
    name_bytes = take(take(1)[0])
    try:
        name = name_bytes.decode()
    except UnicodeDecodeError:
        name = name_bytes.decode(errors="replace")  # a label only; the key id still matches
    wrap = Wrap(key_id=key_id, name=name, ephemeral_public=take(KEY_BYTES), wrapped=take(48))
    return wrap, at


def new_data_key() -> bytes:
    return os.urandom(DATA_KEY_BYTES)


def new_session_uid() -> bytes:
    return os.urandom(SESSION_UID_BYTES)


def _wrap_key(shared: bytes, ephemeral_public: bytes, public: bytes, session_uid: bytes) -> bytes:
    hkdf = HKDF(
        algorithm=hashes.SHA256(),
        length=DATA_KEY_BYTES,
        salt=ephemeral_public + public,
        info=WRAP_INFO + session_uid,
    )
    return hkdf.derive(shared)


def wrap_data_key(data_key: bytes, recipients: Sequence[Recipient], session_uid: bytes) -> KeyBlock:
    """Seal ``data_key`` for each recipient (ephemeral X25519, HKDF-SHA256, AES-256-GCM)."""
    if len(data_key) != DATA_KEY_BYTES or len(session_uid) != SESSION_UID_BYTES:
        raise ValueError("a data key is 32 bytes and a session uid 16")
    if not 1 <= len(recipients) <= MAX_RECIPIENTS:
        raise KeyBlockError(
            f"seal a session for 1 to {MAX_RECIPIENTS} recipients, not {len(recipients)}"
        )
    if len({r.key_id for r in recipients}) != len(recipients):
        raise KeyBlockError("the same recipient key is named twice; name each key once")
    wraps = []
    for r in recipients:
        ephemeral = X25519PrivateKey.generate()
        ephemeral_public = ephemeral.public_key().public_bytes_raw()
        shared = ephemeral.exchange(X25519PublicKey.from_public_bytes(r.public))
        key = _wrap_key(shared, ephemeral_public, r.public, session_uid)
        wrapped = AESGCM(key).encrypt(WRAP_NONCE, data_key, None)
        wraps.append(
            Wrap(key_id=r.key_id, name=r.name, ephemeral_public=ephemeral_public, wrapped=wrapped)
        )
    return KeyBlock(session_uid=session_uid, wraps=tuple(wraps))


def unwrap_data_key(block: KeyBlock, identities: Sequence[Identity]) -> bytes:
    """The data key, opened with the first identity that is one of the block's recipients."""
    for identity in identities:
        me = identity.recipient
        for w in block.wraps:
            if w.key_id != me.key_id:
                continue
            try:
                shared = X25519PrivateKey.from_private_bytes(identity.secret).exchange(
                    X25519PublicKey.from_public_bytes(w.ephemeral_public)
                )
                key = _wrap_key(shared, w.ephemeral_public, me.public, block.session_uid)
                return AESGCM(key).decrypt(WRAP_NONCE, w.wrapped, None)
            except (InvalidTag, ValueError):
                raise KeyBlockError(
                    f"the session's wrap for {w.label()} does not open with {me.label()}: the "
                    "key block is damaged; try another recipient's identity"
                ) from None
    given = ", ".join(_given(i) for i in identities) or "none"
    raise WrongIdentityError(
        f"identity {given} is not one of this session's recipients; open it with the identity "
        f"file of one of: {block.recipients()}"
    )


def _given(identity: Identity) -> str:
    where = f" from {identity.path}" if identity.path else ""
    return f"{identity.recipient.label()}{where}"
