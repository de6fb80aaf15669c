"""Sealed sessions, as a reader relies on them: real HDF5 files written by ``SessionWriter`` with
recipients, read back with each recipient's identity, refused in one line without one or with
someone else's, and every kind of tampering (a changed byte, a frame moved to another row, a
frame copied from another session, a changed recipient list) found and named. ``recover``
copies a sealed session without a key, and the copy opens with the identity."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
import xxhash

from protocol.sealing import (
    OVERHEAD_BYTES,
    IdentityRequiredError,
    WrongIdentityError,
    generate_identity,
)
from protocol.session import (
    CameraInfo,
    ImageChecksumError,
    ImageSealError,
    SessionFormatError,
    SessionReader,
    SessionWriter,
)
from protocol.session.recover import recover_session
from tests.protocol import spec_unsealer

T0_NS = 1_770_000_000_000_000_000
PERIOD_NS = 33_333_333
ROWS = 12
JPEG, RAW = 101, 102
META = {"patient": "Jane Doe, born 1961-04-02", "room": "OR 3"}
RIG = 'rig_name = "or-3"  # Dr. Smith\'s room\nfps = 30\n'


@pytest.fixture(scope="module")
def site():
    return generate_identity("hospital-a")


@pytest.fixture(scope="module")
def escrow():
    return generate_identity("escrow")


def _jpeg(serial: int, row: int, side: int, size: int = 0) -> bytes:
    """A JPEG-shaped image whose first bytes name it: found in the file only if stored plain."""
    head = b"\xff\xd8\xff\xe0\x00\x10JFIF\x00" + f"plain {serial}/{row}/{side}".encode()
    body = np.random.default_rng(serial * 1000 + row * 2 + side).bytes(size or 3_000 + row * 97)
    return head + body + b"\xff\xd9"


def _raw(row: int, side: int) -> bytes:
    return bytes((row * 7 + side + i) % 256 for i in range(8 * 4 * 3))


CAMERAS = [
    CameraInfo(
        camera_serial=JPEG,
        node_id="orin-a",
        resolution="HD1200",
        width=1920,
        height=1200,
        fps_nominal=30.0,
        encoding="jpeg",
    ),
    CameraInfo(
        camera_serial=RAW,
        node_id="orin-a",
        resolution="TINY",
        width=8,
        height=4,
        fps_nominal=30.0,
        encoding="raw_bgr8",
    ),
]


def _images(serial: int, row: int, size: int = 0) -> tuple[bytes, bytes]:
    if serial == RAW:
        return _raw(row, 0), _raw(row, 1)
    return _jpeg(serial, row, 0, size), _jpeg(serial, row, 1, size)


def _write(path: Path, recipients, *, rows: int = ROWS, size: int = 0) -> dict:
    """A session of a JPEG and a raw camera, one set per row; the images written, by camera."""
    written: dict[int, list[tuple[bytes, bytes]]] = {JPEG: [], RAW: []}
    with SessionWriter(
        path,
        session_name="case-7",
        case_metadata=META,
        cameras=CAMERAS,
        tolerance_ns=PERIOD_NS // 2,
        rig_config_text=RIG,
        software_version="test",
        started_unix_ns=T0_NS,
        recipients=recipients,
    ) as w:
        for row in range(rows):
            for serial in (JPEG, RAW):
                images = _images(serial, row, size)
                w.append_frame(
                    serial,
                    left=images[0],
                    right=images[1],
                    capture_unix_ns=T0_NS + row * PERIOD_NS + serial,
                    host_receive_unix_ns=T0_NS + row * PERIOD_NS + 2_000_000,
                    recorder_receive_unix_ns=T0_NS + row * PERIOD_NS + 3_000_000,
                    frame_index=row,
                    seq=row,
                    ptp_offset_ns=0,
                    ptp_locked=True,
                )
                written[serial].append(images)
            times = [T0_NS + row * PERIOD_NS + s for s in (JPEG, RAW)]
            w.append_set(T0_NS + row * PERIOD_NS, [row, row], max(times) - min(times))
            if row % 5 == 4:
                w.flush()
    return written


@pytest.fixture
def sealed(tmp_path, site, escrow):
    path = tmp_path / "case-7.h5"
    return path, _write(path, [site.recipient, escrow.recipient])


def test_a_sealed_session_reads_back_whole_with_each_recipients_identity(sealed, site, escrow):
    path, written = sealed
    for identity in (site, escrow):
        with SessionReader(path, identity=identity) as r:
            assert r.sealed and r.can_open and r.info.sealed
            assert [x.label() for x in r.recipients] == [
                site.recipient.label(),
                escrow.recipient.label(),
            ]
            assert r.info.case_metadata == META and r.case_metadata() == META
            assert r.info.rig_config_toml == RIG and r.rig_config_text() == RIG
            for serial in (JPEG, RAW):
                for row, images in enumerate(written[serial]):
                    assert r.frame_bytes(serial, row) == images
            assert r.verify() == []
            summary = r.summary()
    plain = sum(len(a) + len(b) for frames in written.values() for a, b in frames)
    stored = sum(summary[str(s)]["image_bytes"] for s in (JPEG, RAW))
    assert stored == plain + 2 * 2 * ROWS * OVERHEAD_BYTES  # 29 bytes per sealed image


def test_without_an_identity_the_structure_reads_and_every_sealed_part_refuses_in_one_line(
    sealed, site, escrow
):
    path, _ = sealed
    with SessionReader(path) as r:
        assert r.sealed and not r.can_open
        assert r.info.format_version == 3 and r.info.session_name == "case-7"
        assert r.info.case_metadata == {"patient": "<sealed>", "room": "<sealed>"}
        assert r.info.rig_config_toml == "<sealed>"
        assert r.frame_count(JPEG) == ROWS and r.sets().members.shape == (ROWS, 2)
        assert r.frame_table(RAW)["sealed_row"].tolist() == list(range(ROWS))
        for read in (
            lambda: r.frame_bytes(JPEG, 3),
            lambda: r.image_bytes(RAW, 0, "right"),
            r.case_metadata,
            r.rig_config_text,
        ):
            with pytest.raises(IdentityRequiredError) as caught:
                read()
            message = str(caught.value)
            assert "\n" not in message
            for who in (site, escrow):
                assert who.recipient.name in message and who.recipient.key_id.hex() in message
            assert "--identity FILE" in message and "EGOSURG_IDENTITY" in message
        problems = r.verify()
    assert len(problems) == 1 and problems[0].startswith("note: sealed for hospital-a")


def test_a_wrong_identity_is_refused_in_one_line_naming_the_recipients(sealed, site):
    path, _ = sealed
    with pytest.raises(WrongIdentityError) as caught:
        SessionReader(path, identity=generate_identity("other-site"))
    message = str(caught.value)
    assert "\n" not in message and "other-site" in message
    assert site.recipient.label() in message and "escrow" in message


def test_the_file_holds_no_plaintext_image_metadata_value_or_rig_text(sealed):
    path, written = sealed
    raw = path.read_bytes()
    for serial in (JPEG, RAW):
        for left, right in written[serial]:
            assert left[:24] not in raw and right[:24] not in raw
    for text in ("Jane Doe", "Dr. Smith", "OR 3"):
        assert text.encode() not in raw
    with h5py.File(path, "r") as f:
        for side in ("left", "right"):
            g = f[f"cameras/{JPEG}"]
            data = g[f"{side}_bytes"][:]
            for o in g[f"{side}_offset"][:]:
                assert data[o] == 1 and bytes(data[o + 1 : o + 4]) != b"\xff\xd8\xff"
    h5dump = shutil.which("h5dump")
    if h5dump is None:
        pytest.skip("h5dump is not installed (Debian package hdf5-tools)")
    out = subprocess.run(
        [h5dump, "-d", f"/cameras/{JPEG}/left_bytes", "-s", "0", "-c", "3", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout
    assert "(0): 1," in out and "255, 216, 255" not in out


def _edit(path: Path, serial: int, row: int, side: str, change) -> None:
    """Change one stored image with h5py (``change(bytes) -> bytes`` of the same length) and,
    as a forger would, store its new checksum."""
    with h5py.File(path, "r+") as f:
        g = f[f"cameras/{serial}"]
        o, n = int(g[f"{side}_offset"][row]), int(g[f"{side}_length"][row])
        new = change(g[f"{side}_bytes"][o : o + n].tobytes())
        g[f"{side}_bytes"][o : o + n] = np.frombuffer(new, np.uint8)
        g[f"{side}_xxh3_64"][row] = xxhash.xxh3_64_intdigest(new)


def _flip(data: bytes) -> bytes:
    at = len(data) // 2
    return data[:at] + bytes([data[at] ^ 0x10]) + data[at + 1 :]


def test_a_flipped_ciphertext_byte_is_named_by_camera_and_row_with_and_without_a_key(sealed, site):
    path, _ = sealed
    with h5py.File(path, "r+") as f:
        g = f[f"cameras/{JPEG}"]
        at = int(g["left_offset"][5]) + 100
        g["left_bytes"][at] ^= 0xFF
    want = f"error: camera {JPEG}: left images of rows 5 do not match their checksums"
    with SessionReader(path) as r:
        assert [p for p in r.verify() if p.startswith("error")] == [
            f"{want} (xxh3_64): their bytes changed after they were recorded"
        ]
    with SessionReader(path, identity=site) as r:
        errors = [p for p in r.verify() if p.startswith("error")]
        assert len(errors) == 1 and errors[0].startswith(want)  # not also as unopened
        with pytest.raises(ImageChecksumError, match=f"camera {JPEG} row 5 left"):
            r.frame_bytes(JPEG, 5)
    # the checksum forged too: only the key finds it, and names it
    _edit(path, RAW, 4, "right", _flip)
    with SessionReader(path) as r:
        assert not any(f"camera {RAW}" in p for p in r.verify())
    with SessionReader(path, identity=site) as r:
        assert (
            f"error: camera {RAW}: right images of rows 4 do not open with the session's key"
            in "\n".join(r.verify())
        )
        with pytest.raises(ImageSealError, match=f"camera {RAW} row 4 right image does not open"):
            r.frame_bytes(RAW, 4)
        assert r.frame_bytes(RAW, 3) is not None  # the others still open


def test_a_frame_moved_to_another_row_does_not_open_and_is_named(sealed, site):
    path, _ = sealed
    with h5py.File(path, "r+") as f:  # row 7 made to point at row 3's image, checksum and all
        g = f[f"cameras/{RAW}"]
        for column in ("left_offset", "left_length", "left_xxh3_64"):
            g[column][7] = g[column][3]
    with SessionReader(path, identity=site) as r:
        with pytest.raises(ImageSealError, match=f"camera {RAW} row 7 left image does not open"):
            r.image_bytes(RAW, 7, "left")
        assert r.image_bytes(RAW, 3, "left") == _raw(3, 0)
        assert f"camera {RAW}: left images of rows 7 do not open" in "\n".join(r.verify())


def test_a_frame_copied_from_another_session_does_not_open_and_is_named(tmp_path, site, escrow):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    for path in (a, b):  # the same recipients, cameras, stamps and images: only the key differs
        _write(path, [site.recipient, escrow.recipient], rows=6, size=4_000)
    with h5py.File(a, "r") as f:
        g = f[f"cameras/{JPEG}"]
        o, n = int(g["right_offset"][4]), int(g["right_length"][4])
        stolen = g["right_bytes"][o : o + n].tobytes()
    _edit(b, JPEG, 4, "right", lambda old: stolen if len(old) == len(stolen) else pytest.fail())
    with SessionReader(b, identity=escrow) as r:
        with pytest.raises(ImageSealError, match=f"camera {JPEG} row 4 right image does not open"):
            r.frame_bytes(JPEG, 4)
        assert f"camera {JPEG}: right images of rows 4 do not open" in "\n".join(r.verify())


def test_a_changed_recipient_list_is_refused_when_the_session_opens(sealed, site):
    """Derived data is sealed for ``reader.recipients``: a list edited in the file must not be
    believed (its sealed copy no longer matches)."""
    path, _ = sealed
    with h5py.File(path, "r+") as f:
        text = f["sealing"].attrs["recipients_json"]
        f["sealing"].attrs["recipients_json"] = text.replace("escrow", "attacker")
    with pytest.raises(SessionFormatError, match="list of recipients was changed"):
        SessionReader(path, identity=site)


def test_recover_copies_a_sealed_session_without_a_key_and_the_copy_opens(sealed, site, tmp_path):
    path, written = sealed
    with h5py.File(path, "r+") as f:  # one damaged image: its frame is left out
        g = f[f"cameras/{JPEG}"]
        g["left_bytes"][int(g["left_offset"][5]) + 50] ^= 0xFF
    target = tmp_path / "recovered.h5"
    report = recover_session(path, target)
    assert report.frames_kept == {JPEG: ROWS - 1, RAW: ROWS}
    with h5py.File(path, "r") as src, h5py.File(target, "r") as dst:
        assert dst["sealing/key_block"][:].tobytes() == src["sealing/key_block"][:].tobytes()
    with SessionReader(target) as r:
        assert r.sealed and not r.can_open
    with SessionReader(target, identity=site) as r:
        assert r.info.case_metadata == META and r.info.rig_config_toml == RIG
        kept = [row for row in range(ROWS) if row != 5]
        assert r.frame_table(JPEG)["sealed_row"].tolist() == kept
        for new_row, row in enumerate(kept):
            assert r.frame_bytes(JPEG, new_row) == written[JPEG][row]
        assert r.verify() == []


def test_recover_with_an_identity_also_leaves_out_a_frame_that_does_not_open(
    sealed, site, tmp_path
):
    """A changed image whose checksum was forged too: only the key finds it. Recovered without
    one it is copied (as stored); with one it is left out and said."""
    path, written = sealed
    _edit(path, JPEG, 2, "right", _flip)
    blind = recover_session(path, tmp_path / "blind.h5")
    assert blind.frames_kept[JPEG] == ROWS
    report = recover_session(path, tmp_path / "opened.h5", identity=site)
    assert report.frames_kept == {JPEG: ROWS - 1, RAW: ROWS}
    assert any("1 frames whose images do not open" in p for p in report.problems)
    with SessionReader(tmp_path / "opened.h5", identity=site) as r:
        assert r.frame_bytes(JPEG, 2) == written[JPEG][3] and r.verify() == []
    with pytest.raises(WrongIdentityError):
        recover_session(path, tmp_path / "stranger.h5", identity=generate_identity("stranger"))
    assert not (tmp_path / "stranger.h5").exists()


def test_recover_rebuilds_a_sealed_sessions_damaged_description_and_keeps_its_sealing(
    sealed, site, tmp_path
):
    path, written = sealed
    with h5py.File(path, "r+") as f:  # the reader cannot describe it: salvaged, then rebuilt
        del f.attrs["tolerance_ns"]
    report = recover_session(path, tmp_path / "recovered.h5")
    assert any("tolerance_ns is lost" in p for p in report.problems)
    with SessionReader(tmp_path / "recovered.h5", identity=site) as r:
        assert r.info.case_metadata == META and r.info.rig_config_toml == RIG
        assert r.frame_bytes(JPEG, 3) == written[JPEG][3] and r.verify() == []


def test_a_plaintext_session_is_written_as_before(tmp_path, site):
    path = tmp_path / "plain.h5"
    written = _write(path, [])
    with SessionReader(path, identity=site) as r:  # an identity is not needed, nor used
        assert not r.sealed and r.recipients == [] and r.info.format_version == 2
        assert "sealed_row" not in r.frame_table(JPEG)
        assert r.frame_bytes(JPEG, 2) == written[JPEG][2] and r.verify() == []
    with h5py.File(path, "r") as f:
        assert "sealing" not in f


def test_a_third_party_opens_a_sealed_session_with_plain_h5py_and_the_documented_format(
    sealed, escrow
):
    """docs/session.md ("Sealed sessions") is enough: the key block, the recipients, the
    metadata values and the images read with h5py and opened by ``spec_unsealer`` (written
    from the format alone, importing nothing of egosurg)."""
    path, written = sealed
    with h5py.File(path, "r") as f:
        uid, key = spec_unsealer.unwrap(f["sealing/key_block"][:].tobytes(), escrow.text())
        meta = json.loads(f.attrs["case_metadata_json"])
        value = base64.b64decode(meta["patient"])
        assert (
            spec_unsealer.open_payload(
                key,
                uid,
                value,
                field="metadata/patient",
                camera_serial=0,
                row=0,
                side=2,
                capture_unix_ns=0,
            )
            == META["patient"].encode()
        )
        rig = base64.b64decode(f.attrs["rig_config_toml"])
        assert (
            spec_unsealer.open_payload(
                key,
                uid,
                rig,
                field="rig_config_toml",
                camera_serial=0,
                row=0,
                side=2,
                capture_unix_ns=0,
            )
            == RIG.encode()
        )
        g = f[f"cameras/{JPEG}"]
        for row in (0, 7):
            o, n = int(g["right_offset"][row]), int(g["right_length"][row])
            image = spec_unsealer.open_payload(
                key,
                uid,
                g["right_bytes"][o : o + n].tobytes(),
                field="image",
                camera_serial=JPEG,
                row=int(g["sealed_row"][row]),
                side=1,
                capture_unix_ns=int(g["capture_unix_ns"][row]),
            )
            assert image == written[JPEG][row][1]
