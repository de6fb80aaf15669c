"""Sealing one payload (an image, a metadata value) under the session's data key.

AES-256-GCM with a random 96-bit nonce per payload, and associated data that binds the payload
to where it belongs: the session, the field, the camera, the row, the side and the capture
stamp. A payload moved to another row, camera or session, or changed by one bit, does not open,
and :class:`SealedPayloadError` names the place it was read from. The byte format is in
``protocol.sealing``'s docstring.

Why random nonces and not a counter: a counter must never repeat under one key, which a take
resumed after a crash (same session, same key, a new process) would have to persist and recover
exactly; 96 random bits need no state. NIST SP 800-38D (8.3) bounds one key to 2**32 payloads
with random nonces (a collision chance under 2**-32); a session of 8 stereo cameras at 60 fps
for 24 hours seals about 2**26.3, and :class:`Sealer` refuses past the bound all the same.
"""

from __future__ import annotations

import itertools
import os
import struct
from dataclasses import dataclass
from typing import Literal

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import AESGCM

from protocol.sealing.errors import SealedPayloadError
from protocol.sealing.wrap import DATA_KEY_BYTES, SESSION_UID_BYTES

PAYLOAD_VERSION = 1
PAYLOAD_MAGIC = b"EGSP"
NONCE_BYTES = 12
TAG_BYTES = 16
OVERHEAD_BYTES = 1 + NONCE_BYTES + TAG_BYTES  # version, nonce, tag
MAX_PAYLOADS_PER_KEY = 2**32  # NIST SP 800-38D's bound for random 96-bit nonces
SIDES = {"left": 0, "right": 1, "": 2}
_TAIL = struct.Struct("<QQBq")  # camera serial, row, side, capture stamp


@dataclass(frozen=True, kw_only=True)
class PayloadContext:
    """Where a payload belongs. ``field``: what it is (``image``, ``case_name``,
    ``metadata/<key>``, ...). Session-wide values have ``camera_serial = 0``, ``row = 0``,
    ``side = ""`` and ``capture_unix_ns = 0``."""

    field: str
    camera_serial: int = 0
    row: int = 0
    side: Literal["left", "right", ""] = ""
    capture_unix_ns: int = 0

    def __post_init__(self) -> None:
        if not 1 <= len(self.field.encode()) <= 255:
            raise ValueError(f"payload field {self.field!r}: 1 to 255 bytes of UTF-8")
        if self.side not in SIDES:
            raise ValueError(f"payload side {self.side!r}: 'left', 'right' or ''")
        if not (0 <= self.camera_serial < 2**64 and 0 <= self.row < 2**64):
            raise ValueError("a payload's camera serial and row are unsigned 64-bit numbers")

    def describe(self) -> str:
        if not self.camera_serial:
            return f"{self.field}"
        side = f" {self.side}" if self.side else ""
        return (
            f"{self.field} of camera {self.camera_serial} row {self.row}{side} "
            f"(captured {self.capture_unix_ns} ns)"
        )


def associated_data(session_uid: bytes, ctx: PayloadContext) -> bytes:
    """The bytes a payload is bound to; rebuilt by the reader, never stored."""
    field = ctx.field.encode()
    tail = _TAIL.pack(ctx.camera_serial, ctx.row, SIDES[ctx.side], ctx.capture_unix_ns)
    return b"".join(
        (PAYLOAD_MAGIC, bytes([PAYLOAD_VERSION]), session_uid, bytes([len(field)]), field, tail)
    )


class Sealer:
    """Seals and opens the payloads of one session under its data key. Thread-safe: the
    cipher keeps no state between calls (the count is a bound, not a nonce)."""

    def __init__(self, data_key: bytes, session_uid: bytes) -> None:
        if len(data_key) != DATA_KEY_BYTES or len(session_uid) != SESSION_UID_BYTES:
            raise ValueError("a data key is 32 bytes and a session uid 16")
        self._aead = AESGCM(data_key)
        self._uid = session_uid
        self._sealed = itertools.count()  # next() is atomic: seal_into is called from threads

    @property
    def session_uid(self) -> bytes:
        return self._uid

    def seal(self, payload: bytes | bytearray | memoryview, ctx: PayloadContext) -> bytearray:
        """``version || nonce || ciphertext || tag``, ``OVERHEAD_BYTES`` longer than
        ``payload``. Encrypted in place into the one output buffer: joining the header to a
        returned ciphertext would copy a raw HD1200 image once more and halve the rate."""
        out = bytearray(len(payload) + OVERHEAD_BYTES)
        self.seal_into(payload, ctx, memoryview(out))
        return out

    def seal_into(
        self, payload: bytes | bytearray | memoryview, ctx: PayloadContext, out: memoryview
    ) -> None:
        """``seal``, written into ``out`` (writable, contiguous bytes, exactly
        ``len(payload) + OVERHEAD_BYTES`` long): the session writer seals each image straight
        into the chunk buffer it is stored from, without allocating or copying it. The AEAD
        releases the GIL, so two threads seal two payloads at once."""
        if out.nbytes != len(payload) + OVERHEAD_BYTES:
            raise ValueError(
                f"a sealed payload of {len(payload)} bytes takes {len(payload) + OVERHEAD_BYTES}"
                f" bytes, not {out.nbytes}"
            )
        if next(self._sealed) >= MAX_PAYLOADS_PER_KEY:
            raise RuntimeError("2**32 payloads sealed under one data key: start a new session")
        nonce = os.urandom(NONCE_BYTES)
        out[0] = PAYLOAD_VERSION
        out[1 : 1 + NONCE_BYTES] = nonce
        self._aead.encrypt_into(
            nonce, payload, associated_data(self._uid, ctx), out[1 + NONCE_BYTES :]
        )

    def open(self, sealed: bytes | bytearray | memoryview, ctx: PayloadContext) -> bytes:
        """The payload, or :class:`SealedPayloadError` naming ``ctx`` and what failed."""
        view = memoryview(sealed)
        where = f"{ctx.describe()} in session {self._uid.hex()}"
        if len(view) < OVERHEAD_BYTES:
            raise SealedPayloadError(
                f"{where} is {len(view)} bytes, shorter than any sealed payload "
                f"({OVERHEAD_BYTES}): it is truncated or not sealed"
            )
        if view[0] != PAYLOAD_VERSION:
            raise SealedPayloadError(
                f"{where} has sealing version {view[0]}, not {PAYLOAD_VERSION}: damaged, or "
                "written by a newer egosurg"
            )
        try:
            return self._aead.decrypt(
                view[1 : 1 + NONCE_BYTES], view[1 + NONCE_BYTES :], associated_data(self._uid, ctx)
            )
        except InvalidTag:
            raise SealedPayloadError(
                f"{where} does not open: its bytes were changed, or it was moved here from "
                "another row, camera or session"
            ) from None
