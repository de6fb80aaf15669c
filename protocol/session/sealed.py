"""A sealed session: what it stores, and the one place its payloads are sealed and opened.

A session written with recipients (``SessionWriter(..., recipients=[...])``) is *sealed*:
``format_version`` 3 and a ``/sealing`` group holding the session's key block (its data key
wrapped for each recipient, ``protocol.sealing``) and the recipients' public keys. Every payload
that can show or name a patient is stored sealed under the data key: each image, in its byte
dataset where the plaintext image would be (so ``h5dump`` shows ciphertext and the stored
checksum covers the ciphertext), each case metadata value, and the rig text (its comments are
free text). The writer holds no key that opens what it wrote: it forgets the data key when it
closes, and the file keeps it only wrapped.

What stays readable without a key, so that ``session info`` and ``verify``'s structure checks
work anywhere: the session name (it is also the file's name, so sealing it would hide nothing),
the metadata *keys*, the camera descriptions (serials, modes, factory calibration: the camera,
not the patient), every table (times, counters, offsets, checksums), the sets, gaps, events and
summary. docs/session.md ("Sealed sessions") is the format, exactly.

Speed. Sealing is AES-GCM at about 2.5-3 GB/s a core here, so an image's AEAD (110-130 us for a
325 kB JPEG) is most of what sealing adds; around it, each image is sealed straight into the
chunk buffer it is stored from where it fits (no allocation, no copy), and a frame's two images
are sealed at once, the left one on a sealing thread (the AEAD releases the GIL), so the thread
that appends (the recorder's session-queue thread) carries about half the cipher's cost
(BENCHMARKS.md, "Sealing"; docs/session.md, "Performance").

Images are bound to ``sealed_row``, a frame table column, rather than to the row itself: the two
are equal in a recorded file, and ``recover`` (which holds no key) keeps each frame's original
``sealed_row`` when it leaves damaged frames out. Moving an image to another row still fails its
tag: the row's ``sealed_row`` and capture stamp are not the image's.
"""

from __future__ import annotations

import base64
import binascii
import json
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import h5py
import numpy as np

from protocol.os_thread import name_os_thread
from protocol.sealing import (
    IDENTITY_ENV,
    OVERHEAD_BYTES,
    Identity,
    IdentityRequiredError,
    KeyBlock,
    KeyBlockError,
    PayloadContext,
    Recipient,
    Sealer,
    new_data_key,
    new_session_uid,
    unwrap_data_key,
    wrap_data_key,
)
from protocol.session.format import SessionFormatError

if TYPE_CHECKING:
    from protocol.session.datasets import Blob

GROUP = "sealing"
KEY_BLOCK = "key_block"
RECIPIENTS_SEALED = "recipients_sealed"
RECIPIENTS_JSON = "recipients_json"
IMAGE_FIELD = "image"
RIG_FIELD = "rig_config_toml"
RECIPIENTS_FIELD = "recipients"
SEALED_TEXT = "<sealed>"  # what a reader without an identity sees for a sealed value
_SIDES: tuple[Literal["left", "right"], ...] = ("left", "right")
# a frame smaller than this is sealed on the calling thread: handing half of it to the sealing
# thread costs more than sealing it (about 30 us of a 2.8 GB/s AEAD)
_PARALLEL_MIN_BYTES = 64 << 10
_MAX_KEY_BLOCK_BYTES = 1 << 16  # 16 recipients take under 2 KiB: more is damage


def metadata_field(key: str) -> str:
    return f"metadata/{key}"


def _b64(data: bytes | bytearray) -> str:
    return base64.b64encode(bytes(data)).decode("ascii")


@dataclass(frozen=True, kw_only=True)
class StoredSeal:
    """A sealed session's sealing exactly as stored: what ``recover`` copies (it holds no key).
    ``case_metadata`` and ``rig_config`` are the root attributes' values (base64 of sealed
    payloads); ``recipients_sealed`` authenticates ``recipients_json`` under the data key."""

    key_block: bytes
    recipients_json: str
    recipients_sealed: bytes
    case_metadata: dict[str, str]
    rig_config: str


def recipients_to_json(recipients: Sequence[Recipient]) -> str:
    return json.dumps(
        [
            {
                "name": r.name,
                "kind": r.kind,
                "key_id": r.key_id.hex(),
                "public": base64.b64encode(r.public).decode("ascii"),
            }
            for r in recipients
        ]
    )


def recipients_from_json(text: str) -> list[Recipient]:
    """The recipients stored in a session; ``ValueError`` for anything but the documented list."""
    items = json.loads(text)
    if not isinstance(items, list) or not items:
        raise ValueError("recipients_json is not a list of recipients")
    out = []
    for item in items:
        public = base64.b64decode(item["public"], validate=True)
        r = Recipient(name=item["name"], kind=item["kind"], public=public)
        if item["key_id"] != r.key_id.hex():
            raise ValueError(f"recipient {r.name}: key_id is not its public key's")
        out.append(r)
    return out


class WriterSeal:
    """The writer's side: a new session's key block and sealer, or a copied session's sealing
    (``recover``), which has no sealer and takes only images sealed already."""

    def __init__(self, sealer: Sealer | None, stored: StoredSeal) -> None:
        self.sealer = sealer
        self.stored = stored
        self._scratch: dict[str, bytearray] = {}  # by side: images that do not fit in place
        self._executor: ThreadPoolExecutor | None = None

    @classmethod
    def new(
        cls, recipients: Sequence[Recipient], case_metadata: Mapping[str, str], rig_config: str
    ) -> WriterSeal:
        """A fresh data key and session uid, wrapped for ``recipients`` (``KeyBlockError`` for
        none, more than 16, or one named twice); the root's sealed values."""
        uid, data_key = new_session_uid(), new_data_key()
        block = wrap_data_key(data_key, recipients, uid)
        sealer = Sealer(data_key, uid)
        listed = recipients_to_json(recipients)
        metadata = {
            k: _b64(sealer.seal(v.encode(), PayloadContext(field=metadata_field(k))))
            for k, v in case_metadata.items()
        }
        stored = StoredSeal(
            key_block=block.to_bytes(),
            recipients_json=listed,
            recipients_sealed=bytes(
                sealer.seal(listed.encode(), PayloadContext(field=RECIPIENTS_FIELD))
            ),
            case_metadata=metadata,
            rig_config=_b64(sealer.seal(rig_config.encode(), PayloadContext(field=RIG_FIELD))),
        )
        return cls(sealer, stored)

    def store_pair(
        self,
        blobs: tuple[Blob, Blob],
        images: tuple[object, object],
        *,
        camera_serial: int,
        row: int,
        capture_unix_ns: int,
    ) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Seal a frame's two images for their row, sides and capture stamp and append them to
        their blobs: (offset, length, XXH3-64 of the sealed bytes) of each. Each is sealed
        straight into its chunk buffer when it fits in what is left of the chunk, else into a
        buffer kept for the side and copied from there (across a chunk boundary, or larger
        than a chunk). Large images are sealed at once, the left one on the sealing thread:
        the AEAD releases the GIL."""
        sealer = self.sealer
        if sealer is None:
            raise ValueError(
                "this session copies a sealed session: append images sealed already "
                "(append_sealed_frame)"
            )
        jobs = []
        for blob, data, side in zip(blobs, images, _SIDES, strict=True):
            src = memoryview(data).cast("B")  # type: ignore[arg-type]
            n = src.nbytes + OVERHEAD_BYTES
            ctx = PayloadContext(
                field=IMAGE_FIELD,
                camera_serial=camera_serial,
                row=row,
                side=side,
                capture_unix_ns=capture_unix_ns,
            )
            dest = blob.reserve(n)
            jobs.append((src, ctx, dest if dest is not None else self._scratch_for(side, n), dest))
        (lsrc, lctx, lout, _), (rsrc, rctx, rout, _) = jobs
        if lsrc.nbytes + rsrc.nbytes >= _PARALLEL_MIN_BYTES:
            left_done = self._pool().submit(sealer.seal_into, lsrc, lctx, lout)
            try:
                sealer.seal_into(rsrc, rctx, rout)
            finally:  # never leave the thread writing into a buffer after an error here
                wait([left_done])
            left_done.result()
        else:
            sealer.seal_into(lsrc, lctx, lout)
            sealer.seal_into(rsrc, rctx, rout)
        left, right = (
            blob.commit(out.nbytes) if dest is not None else blob.append(out)
            for blob, (_, _, out, dest) in zip(blobs, jobs, strict=True)
        )
        return left, right

    def _scratch_for(self, side: str, n: int) -> memoryview:
        scratch = self._scratch.get(side)
        if scratch is None or len(scratch) < n:
            scratch = self._scratch[side] = bytearray(n)
        return memoryview(scratch)[:n]

    def _pool(self) -> ThreadPoolExecutor:
        if self._executor is None:
            self._executor = ThreadPoolExecutor(
                1, "session-seal", initializer=name_os_thread, initargs=("session-seal",)
            )
        return self._executor

    def forget(self) -> None:
        """Drop the data key (the writer is done) and stop the sealing thread."""
        self.sealer = None
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def write(self, f: h5py.File) -> None:
        """The ``/sealing`` group (before the file turns SWMR: nothing is added later)."""
        g = f.create_group(GROUP)
        g.create_dataset(KEY_BLOCK, data=np.frombuffer(self.stored.key_block, np.uint8))
        g.create_dataset(
            RECIPIENTS_SEALED, data=np.frombuffer(self.stored.recipients_sealed, np.uint8)
        )
        g.attrs[RECIPIENTS_JSON] = self.stored.recipients_json


def read_stored_seal(f: h5py.File, case_metadata_json: str, rig_config: str) -> StoredSeal:
    """The sealing of an open sealed session as stored, given its two sealed root attributes
    as read; ``KeyError``/``ValueError`` where it is missing or damaged."""
    g = f[GROUP]
    metadata = json.loads(case_metadata_json or "{}")
    if not isinstance(metadata, dict) or not all(isinstance(v, str) for v in metadata.values()):
        raise ValueError("case_metadata_json is not a JSON object of text values")
    raw = g.attrs[RECIPIENTS_JSON]
    return StoredSeal(
        key_block=_bytes(g[KEY_BLOCK]),
        recipients_json=raw.decode() if isinstance(raw, bytes) else str(raw),
        recipients_sealed=_bytes(g[RECIPIENTS_SEALED]),
        case_metadata=metadata,
        rig_config=rig_config,
    )


def _bytes(ds: h5py.Dataset) -> bytes:
    if ds.ndim != 1 or ds.dtype != np.uint8 or ds.shape[0] > _MAX_KEY_BLOCK_BYTES:
        raise ValueError(f"{ds.name} has shape {ds.shape} and type {ds.dtype}")
    return np.asarray(ds[:]).tobytes()


class ReaderSeal:
    """The reader's side: the key block and recipients of a sealed session, and with an
    identity the sealer that opens its payloads."""

    def __init__(self, path: Path, stored: StoredSeal, identity: Identity | None) -> None:
        self.path = path
        self.stored = stored
        try:
            self.block = KeyBlock.from_bytes(stored.key_block)
        except KeyBlockError as exc:
            raise SessionFormatError(
                f"{path}: its key block is damaged ({exc}); no identity can open its images. "
                "Copy the file again from the recorder"
            ) from None
        try:
            self.recipients = recipients_from_json(stored.recipients_json)
        except (ValueError, TypeError, KeyError, binascii.Error) as exc:
            raise SessionFormatError(
                f"{path}: its list of recipients is damaged ({exc}); copy the file again"
            ) from None
        if sorted(r.key_id for r in self.recipients) != sorted(w.key_id for w in self.block.wraps):
            raise SessionFormatError(
                f"{path}: its recipients ({', '.join(r.label() for r in self.recipients)}) are "
                f"not those its key block is wrapped for ({self.block.recipients()}); the file "
                "was changed"
            )
        self.sealer: Sealer | None = None
        if identity is not None:
            key = unwrap_data_key(self.block, [identity])  # WrongIdentityError names them
            self.sealer = Sealer(key, self.block.session_uid)
            listed = self.open(stored.recipients_sealed, PayloadContext(field=RECIPIENTS_FIELD))
            if listed != stored.recipients_json.encode():
                raise SessionFormatError(
                    f"{path}: its list of recipients was changed after it was recorded (it no "
                    "longer matches the sealed copy); do not seal derived data for it"
                )

    def required(self, what: str) -> IdentityRequiredError:
        return IdentityRequiredError(
            f"{self.path}: {what} is sealed; open the session with the identity of one of its "
            f"recipients, {self.block.recipients()}: pass --identity FILE or set {IDENTITY_ENV}"
        )

    def open(self, sealed: bytes | bytearray | memoryview, ctx: PayloadContext) -> bytes:
        """The payload (``SealedPayloadError`` if it does not open there);
        ``IdentityRequiredError`` without an identity."""
        if self.sealer is None:
            raise self.required(ctx.describe())
        return self.sealer.open(sealed, ctx)

    def open_metadata(self) -> dict[str, str]:
        out = {}
        for key, value in self.stored.case_metadata.items():
            raw = _unb64(value, self.path, metadata_field(key))
            out[key] = self.open(raw, PayloadContext(field=metadata_field(key))).decode()
        return out

    def open_rig_config(self) -> str:
        raw = _unb64(self.stored.rig_config, self.path, RIG_FIELD)
        return self.open(raw, PayloadContext(field=RIG_FIELD)).decode()


def _unb64(value: str, path: Path, field: str) -> bytes:
    try:
        return base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise SessionFormatError(
            f"{path}: the sealed {field} is not base64; it was changed"
        ) from None
