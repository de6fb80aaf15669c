"""Sealed derived files (``protocol.sealing.derived``): what a case's models and cached depth
rely on. A file opens with any recipient's identity and from the documented format alone; it
does not open as another timestamp, another role or another session's, and says so; a changed
byte is found without a key; without an identity the refusal names the recipients."""

from __future__ import annotations

import struct

import pytest
import xxhash

from protocol.sealing import (
    IdentityRequiredError,
    SealedPayloadError,
    WrongIdentityError,
    generate_identity,
    new_session_uid,
)
from protocol.sealing.derived import DerivedSeal, check_sealed_file, is_sealed_file
from tests.protocol import spec_unsealer

PLAIN = b"PK\x03\x04 a model's zip, with a patient's silhouette in it " * 200


@pytest.fixture(scope="module")
def keys():
    return generate_identity("hospital-a"), generate_identity("escrow"), generate_identity("x")


def _seal(keys, uid: bytes, identity=None) -> DerivedSeal:
    site, escrow, _ = keys
    return DerivedSeal(uid, [site.recipient, escrow.recipient], identity)


def test_a_sealed_file_opens_with_each_recipient_and_holds_no_plaintext(keys):
    uid = new_session_uid()
    raw = _seal(keys, uid).seal("model", "t00002.000", PLAIN)
    assert is_sealed_file(raw) and b"PK\x03\x04" not in raw and b"patient" not in raw
    for identity in keys[:2]:
        assert _seal(keys, uid, identity).open("model", "t00002.000", raw, "m") == PLAIN
    # each file has its own data key: the same model sealed twice shares no ciphertext
    again = _seal(keys, uid).seal("model", "t00002.000", PLAIN)
    assert raw[-200:] != again[-200:]


def test_a_file_opens_from_the_documented_format_alone(keys):
    """The docstring's table, read with ``cryptography`` and ``xxhash`` only."""
    site = keys[0]
    uid = new_session_uid()
    raw = _seal(keys, uid).seal("depth", "ab" * 16, PLAIN)
    magic, version, role, k = struct.unpack_from("<4sBBH", raw)
    assert (magic, version, role) == (b"EGSD", 1, 2)
    (checksum,) = struct.unpack_from("<Q", raw, len(raw) - 8)
    assert xxhash.xxh3_64_intdigest(raw[:-8]) == checksum
    block, payload = raw[8 : 8 + k], raw[8 + k : -8]
    got_uid, data_key = spec_unsealer.unwrap(block, site.text())
    assert got_uid == uid
    opened = spec_unsealer.open_payload(
        data_key, uid, payload, field=f"depth/{'ab' * 16}", camera_serial=0, row=0, side=2,
        capture_unix_ns=0,
    )  # fmt: skip
    assert opened == PLAIN


def test_a_file_moved_to_another_name_role_or_session_does_not_open_and_says_which(keys):
    site = keys[0]
    uid = new_session_uid()
    raw = _seal(keys, uid).seal("model", "t00002.000", PLAIN)
    reader = _seal(keys, uid, site)
    with pytest.raises(SealedPayloadError, match=r"does not open as model t00003\.000") as e:
        reader.open("model", "t00003.000", raw, "case/models/t00003.000.npz.sealed")
    assert "case/models/t00003.000.npz.sealed" in str(e.value) and "another timestamp" in str(
        e.value
    )
    with pytest.raises(SealedPayloadError, match="is a sealed model, not a depth"):
        reader.open("depth", "t00002.000", raw, "f")
    other = _seal(keys, new_session_uid(), site)
    with pytest.raises(SealedPayloadError, match="sealed for another session"):
        other.open("model", "t00002.000", raw, "f")


def test_a_changed_byte_is_found_without_a_key(keys):
    uid = new_session_uid()
    raw = bytearray(_seal(keys, uid).seal("model", "t1", PLAIN))
    assert "hospital-a" in check_sealed_file(bytes(raw), "m")
    for at in (5, 40, len(raw) // 2, len(raw) - 9):
        bad = bytearray(raw)
        bad[at] ^= 0x01
        with pytest.raises(SealedPayloadError, match="m fails its checksum"):
            check_sealed_file(bytes(bad), "m")
    with pytest.raises(SealedPayloadError, match="not a sealed egosurg file"):
        check_sealed_file(PLAIN, "m")
    with pytest.raises(SealedPayloadError, match="cut short"):
        check_sealed_file(bytes(raw[:10]), "m")


def test_without_an_identity_or_with_another_the_refusal_names_the_recipients(keys):
    uid = new_session_uid()
    raw = _seal(keys, uid).seal("model", "t1", PLAIN)
    with pytest.raises(IdentityRequiredError) as e:
        _seal(keys, uid).open("model", "t1", raw, "case/models/t1.npz.sealed")
    text = str(e.value)
    assert "\n" not in text and "hospital-a (key id" in text and "escrow (key id" in text
    assert "--identity FILE" in text and "EGOSURG_IDENTITY" in text
    with pytest.raises(WrongIdentityError, match="hospital-a"):
        _seal(keys, uid, keys[2]).open("model", "t1", raw, "f")
