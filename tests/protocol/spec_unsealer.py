"""A third party's unsealer, written from protocol/sealing/__init__.py's docstring alone.

It imports nothing of egosurg, only the standard library and ``cryptography``: if the
documented format and the code part ways, tests/protocol/test_sealing.py fails here.
"""

from __future__ import annotations

import base64
import hashlib
import struct

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import AESGCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF


def read_identity(text: str) -> tuple[bytes, bytes, bytes]:
    """(secret, public, key id) of an identity file's text."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    assert lines[0] == "egosurg-identity v1", lines[0]
    fields = dict(ln.split(":", 1) for ln in lines[1:])
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    secret = base64.b64decode(fields["secret"], validate=True)
    public = base64.b64decode(fields["public"], validate=True)
    key_id = hashlib.sha256(b"egosurg-recipient v1" + public).digest()[:8]
    assert key_id.hex() == fields["key-id"]
    return secret, public, key_id


def unwrap(block: bytes, identity_text: str) -> tuple[bytes, bytes]:
    """(session uid, data key) of a key block, opened with an identity file's text."""
    secret, public, key_id = read_identity(identity_text)
    magic, version, uid, count = struct.unpack_from("<4sB16sB", block, 0)
    assert (magic, version) == (b"EGSK", 1)
    at = 22
    for _ in range(count):
        wrap_id = block[at : at + 8]
        name_len = block[at + 8]
        at += 9 + name_len
        ephemeral, wrapped = block[at : at + 32], block[at + 32 : at + 80]
        at += 80
        if wrap_id != key_id:
            continue
        shared = X25519PrivateKey.from_private_bytes(secret).exchange(
            X25519PublicKey.from_public_bytes(ephemeral)
        )
        wrap_key = HKDF(
            algorithm=hashes.SHA256(),
            length=32,
            salt=ephemeral + public,
            info=b"egosurg data key wrap v1" + uid,
        ).derive(shared)
        return uid, AESGCM(wrap_key).decrypt(bytes(12), wrapped, b"")
    raise LookupError("this identity is not one of the key block's recipients")


def open_payload(
    data_key: bytes,
    uid: bytes,
    sealed: bytes,
    *,
    field: str,
    camera_serial: int,
    row: int,
    side: int,
    capture_unix_ns: int,
) -> bytes:
    """A sealed payload's plaintext; ``side`` 0 left, 1 right, 2 none."""
    name = field.encode()
    aad = (
        b"EGSP"
        + bytes([1])
        + uid
        + bytes([len(name)])
        + name
        + struct.pack("<QQBq", camera_serial, row, side, capture_unix_ns)
    )
    assert sealed[0] == 1
    return AESGCM(data_key).decrypt(sealed[1:13], sealed[13:], aad)
