"""Sealed payloads and the session's key block, as a reader relies on them: every recipient opens
a session, nobody else does, and a payload that was changed, moved to another row or camera, or
copied from another session does not open and is named. A decryptor written from the documented
format alone (``spec_unsealer``) opens what the code seals."""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest

from protocol.sealing import (
    KeyBlock,
    KeyBlockError,
    PayloadContext,
    SealedPayloadError,
    Sealer,
    WrongIdentityError,
    generate_identity,
    load_identity,
    new_data_key,
    new_session_uid,
    unwrap_data_key,
    wrap_data_key,
    write_identity,
)
from tests.protocol import spec_unsealer

SERIAL = 41234567
IMAGE = PayloadContext(
    field="image", camera_serial=SERIAL, row=17, side="left", capture_unix_ns=1_764_000_000_5
)


@pytest.fixture(scope="module")
def site():
    return generate_identity("hospital-a")


@pytest.fixture(scope="module")
def escrow():
    return generate_identity("escrow")


@pytest.fixture
def session(site, escrow):
    """(sealer, key block bytes) of a fresh session sealed for the site and the escrow key."""
    uid, data_key = new_session_uid(), new_data_key()
    block = wrap_data_key(data_key, [site.recipient, escrow.recipient], uid).to_bytes()
    return Sealer(data_key, uid), block


def _reader(block: bytes, *identities) -> Sealer:
    parsed = KeyBlock.from_bytes(block)
    return Sealer(unwrap_data_key(parsed, identities), parsed.session_uid)


def test_a_sealed_image_opens_for_each_recipient_and_hides_its_bytes(session, site, escrow):
    sealer, block = session
    image = os.urandom(1920 * 1200 * 3 // 16)
    sealed = sealer.seal(image, IMAGE)
    assert image[:64] not in sealed and len(sealed) == len(image) + 29
    for who in (site, escrow):
        assert _reader(block, who).open(sealed, IMAGE) == image
    empty = PayloadContext(field="case_name")
    assert _reader(block, site).open(sealer.seal(b"", empty), empty) == b""


def test_the_same_payload_sealed_twice_differs(session):
    """A fresh nonce per payload: equal frames (a covered lens) do not show as equal bytes."""
    sealer, _ = session
    assert sealer.seal(b"x" * 100, IMAGE) != sealer.seal(b"x" * 100, IMAGE)


def test_a_wrong_identity_is_one_line_naming_the_sessions_recipients(session):
    _, block = session
    stranger = generate_identity("other-site")
    with pytest.raises(WrongIdentityError) as caught:
        _reader(block, stranger)
    message = str(caught.value)
    assert "\n" not in message and "other-site" in message
    parsed = KeyBlock.from_bytes(block)
    for wrap in parsed.wraps:
        assert wrap.name in message and wrap.key_id.hex() in message


@pytest.mark.parametrize(
    "where", [0, 1, 13, 1000, -1], ids=["version", "nonce", "data", "mid", "tag"]
)
def test_a_changed_byte_anywhere_is_named_by_camera_and_row(session, site, where):
    sealer, block = session
    sealed = bytearray(sealer.seal(os.urandom(4096), IMAGE))
    sealed[where] ^= 0x01
    with pytest.raises(SealedPayloadError, match=f"camera {SERIAL} row 17 left"):
        _reader(block, site).open(bytes(sealed), IMAGE)


@pytest.mark.parametrize(
    "moved",
    [
        {"row": 18},
        {"camera_serial": SERIAL + 1},
        {"side": "right"},
        {"capture_unix_ns": IMAGE.capture_unix_ns + 1},
        {"field": "depth"},
    ],
    ids=["row", "camera", "side", "stamp", "field"],
)
def test_a_payload_moved_to_another_place_does_not_open(session, site, moved):
    sealer, block = session
    sealed = sealer.seal(b"frame bytes", IMAGE)
    there = PayloadContext(**{**IMAGE.__dict__, **moved})
    with pytest.raises(SealedPayloadError, match="moved here from another row") as caught:
        _reader(block, site).open(sealed, there)
    assert there.describe() in str(caught.value)


def test_a_payload_copied_from_another_session_does_not_open(session, site):
    """Even under the same data key: the session uid is bound in, not only the key."""
    _, block = session
    other = wrap_data_key(new_data_key(), [site.recipient], new_session_uid()).to_bytes()
    sealed_elsewhere = _reader(other, site).seal(b"frame", IMAGE)
    with pytest.raises(SealedPayloadError, match="another row, camera or session"):
        _reader(block, site).open(sealed_elsewhere, IMAGE)
    same_key_other_uid = Sealer(
        unwrap_data_key(KeyBlock.from_bytes(block), [site]), new_session_uid()
    ).seal(b"frame", IMAGE)
    with pytest.raises(SealedPayloadError):
        _reader(block, site).open(same_key_other_uid, IMAGE)


def test_a_truncated_payload_is_named(session, site):
    _, block = session
    with pytest.raises(SealedPayloadError, match="shorter than any sealed payload"):
        _reader(block, site).open(b"\x01" * 10, IMAGE)


def test_a_damaged_key_block_is_one_line(session, escrow):
    _, block = session
    for broken in (block[:20], block[:-1], block + b"\x00", b"EGSX" + block[4:]):
        with pytest.raises(KeyBlockError):
            KeyBlock.from_bytes(broken)
    tampered = bytearray(block)
    tampered[-1] ^= 0x80  # inside the last wrap's tag
    parsed = KeyBlock.from_bytes(bytes(tampered))
    with pytest.raises(KeyBlockError, match="damaged"):
        unwrap_data_key(parsed, [escrow])


def test_a_third_party_opens_a_session_from_the_documented_format(tmp_path, session, site):
    """spec_unsealer was written from protocol/sealing/__init__.py's docstring; it reads the
    identity file as written to disk, unwraps the key block and opens payloads."""
    sealer, block = session
    _, identity_path = write_identity(site, tmp_path / "keys")
    uid, data_key = spec_unsealer.unwrap(block, identity_path.read_text())
    right = PayloadContext(
        field="image", camera_serial=SERIAL, row=3, side="right", capture_unix_ns=-5
    )
    meta = PayloadContext(field="metadata/surgeon")
    image = os.urandom(3000)
    assert (
        spec_unsealer.open_payload(
            data_key,
            uid,
            sealer.seal(image, right),
            field="image",
            camera_serial=SERIAL,
            row=3,
            side=1,
            capture_unix_ns=-5,
        )
        == image
    )
    assert (
        spec_unsealer.open_payload(
            data_key,
            uid,
            sealer.seal("Dr Ødegård".encode(), meta),
            field="metadata/surgeon",
            camera_serial=0,
            row=0,
            side=2,
            capture_unix_ns=0,
        ).decode()
        == "Dr Ødegård"
    )
    assert load_identity(identity_path).recipient == site.recipient


def test_the_third_party_unsealer_imports_nothing_of_egosurg():
    tree = ast.parse(Path(spec_unsealer.__file__).read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            roots.add((node.module or "").split(".")[0])
    assert roots <= {"__future__", "base64", "hashlib", "struct", "cryptography"}, roots
