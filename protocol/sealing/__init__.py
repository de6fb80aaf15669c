"""Sealing: session data encrypted for chosen recipients, with keys only readers hold.

A recorder seals a session for one or more **recipients** (X25519 public keys: a site's
reconstruction workstation, an escrow key kept offline). Each session has a fresh 32-byte
**data key**; every payload that can show a patient (an image, a case name, a metadata value) is
sealed under it with AES-256-GCM, and the data key is kept only wrapped for each recipient, so
the recorder holds no key that opens what it wrote. Losing every recipient's identity loses the
sessions sealed for them: keep two recipients, one of them offline. Built on the
``cryptography`` library's X25519, HKDF-SHA256 and AES-256-GCM; nothing here is its own
cryptography. This module needs only the edge's libraries (the recorder seals).

This docstring is the format: a third party with an identity file can open a session's payloads
from it alone (``tests/protocol/spec_unsealer.py`` does, importing only ``cryptography``).
Integers are little-endian; ``||`` joins bytes.

Identity and recipient files
----------------------------
UTF-8 text. Lines starting with ``#`` are comments; blank lines are skipped. The first other
line is the header, ``egosurg-identity v1`` (secret file, ``NAME.identity``, mode 0600) or
``egosurg-recipient v1`` (public file, ``NAME.recipient``). Then ``field: value`` lines, each
field once: ``kind`` (``site``), ``name`` (1-32 of ``A-Za-z0-9_.-``, starting with a letter or
digit), ``key-id`` (16 lower-case hex digits), ``public`` (standard base64 of the 32-byte X25519
public key) and, in an identity file only, ``secret`` (standard base64 of the 32-byte X25519
secret key). ``key-id`` = the first 8 bytes of SHA-256(``b"egosurg-recipient v1"`` || public).

Key block (the session's data key, wrapped)
-------------------------------------------
=======  ==========  ===========================================================
offset   bytes       content
=======  ==========  ===========================================================
0        4           magic ``b"EGSK"``
4        1           version, 1
5        16          session uid (random; every payload's associated data holds it)
21       1           n, the number of wraps (1 to 16)
22       ...         n wraps, one after another
=======  ==========  ===========================================================

Each wrap: key id (8 bytes) || name length L (1 byte) || name (L bytes of UTF-8: a label for
messages, not authenticated) || ephemeral public key E (32 bytes) || wrapped key W (48 bytes).
No bytes follow the last wrap.

To unwrap with an identity (secret s, public R, key id K): take the wrap whose key id is K;
``shared = X25519(s, E)``; ``wrap_key = HKDF-SHA256(ikm=shared, salt=E || R, info=b"egosurg
data key wrap v1" || session uid, length=32)``; ``data_key = AES-256-GCM-decrypt(wrap_key,
nonce=12 zero bytes, ciphertext || tag = W, associated data empty)`` (32 bytes). The zero nonce
is safe because each wrap key is used once: E is fresh for every wrap. Wrapping is the mirror:
a fresh X25519 key pair (e, E) per recipient, ``shared = X25519(e, R)``, the same HKDF.

Sealed payload
--------------
``version (1 byte, 1) || nonce (12 bytes, random per payload) || AES-256-GCM ciphertext (as
long as the payload) || tag (16 bytes)``, under the data key, with the associated data:

=======  ==========  ===========================================================
offset   bytes       content
=======  ==========  ===========================================================
0        4           ``b"EGSP"``
4        1           version, 1
5        16          session uid (from the key block)
21       1           F, the length of the field name
22       F           field name, UTF-8: ``image``, ``case_name``, ``metadata/<key>``, ...
22+F     8           camera serial, u64 (0 for a session-wide value)
30+F     8           row of the camera's table, u64 (0 for a session-wide value)
38+F     1           side: 0 left, 1 right, 2 none
39+F     8           capture stamp, i64 nanoseconds since the Unix epoch (0 if none)
=======  ==========  ===========================================================

The associated data is never stored: the reader rebuilds it from where it read the payload, so
a payload moved to another row, camera, side, field or session fails its tag. Nonces are random
(not a counter) so that a take resumed by a new process needs no nonce state; one data key
seals at most 2**32 payloads (NIST SP 800-38D, 8.3), a bound the sealer enforces.
"""

from __future__ import annotations

from protocol.sealing.errors import (
    IdentityError,
    IdentityRequiredError,
    KeyBlockError,
    SealedPayloadError,
    WrongIdentityError,
)
from protocol.sealing.keyfiles import (
    IDENTITY_ENV,
    IDENTITY_SUFFIX,
    KINDS,
    RECIPIENT_SUFFIX,
    Identity,
    Recipient,
    generate_identity,
    load_identity,
    load_recipient,
    write_identity,
)
from protocol.sealing.payload import OVERHEAD_BYTES, PayloadContext, Sealer
from protocol.sealing.wrap import (
    KeyBlock,
    new_data_key,
    new_session_uid,
    unwrap_data_key,
    wrap_data_key,
)

__all__ = [
    "IDENTITY_ENV",
    "IDENTITY_SUFFIX",
    "KINDS",
    "OVERHEAD_BYTES",
    "RECIPIENT_SUFFIX",
    "Identity",
    "IdentityError",
    "IdentityRequiredError",
    "KeyBlock",
    "KeyBlockError",
    "PayloadContext",
    "Recipient",
    "SealedPayloadError",
    "Sealer",
    "WrongIdentityError",
    "generate_identity",
    "load_identity",
    "load_recipient",
    "new_data_key",
    "new_session_uid",
    "unwrap_data_key",
    "wrap_data_key",
    "write_identity",
]
