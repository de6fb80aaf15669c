"""Damaged data is never used unnoticed: a changed image is caught wherever it is read, named by
camera, row and side; ``session recover`` saves every intact frame of a file whose root
attributes or one camera's header are damaged, and says what it skipped and why.

Real files (written by ``SessionWriter``, damaged with plain file writes or h5py), the real
``egosurg`` command in a subprocess; what recover keeps is counted against plain h5py's own
reading of the damaged file."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import xxhash

from protocol.session import ImageChecksumError, SessionFormatError, SessionReader
from protocol.session.recover import recover_session
from tests.conftest import run_egosurg
from tests.protocol.test_session import _write_session
from tests.protocol.test_session_damage import _zeroed_string_header

INTACT = {101: 60, 102: 51, 103: 60}  # frames per camera in the clean file


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("integrity") / "clean.h5"
    _write_session(path, rows=60)
    return path


def _flip_image_byte(path: Path, serial: int, row: int, side: str) -> None:
    """One byte in the middle of one image: its markers and size unchanged, only its checksum
    can tell."""
    with h5py.File(path, "r+") as f:
        g = f[f"cameras/{serial}"]
        off, n = int(g[f"{side}_offset"][row]), int(g[f"{side}_length"][row])
        g[f"{side}_bytes"][off + n // 2] ^= 0x01


def _h5py_intact(path: Path) -> dict[int, int]:
    """Per camera, the frames plain h5py reads whose two images match their stored checksums;
    a camera whose group h5py cannot open counts 0."""
    out = {}
    with h5py.File(path, "r") as f:
        for name in f["cameras"]:
            try:
                g = f[f"cameras/{name}"]
                n = min(g[c].shape[0] for c in ("left_offset", "left_xxh3_64", "right_offset"))
                ok = 0
                for row in range(n):
                    ok += all(
                        xxhash.xxh3_64_intdigest(
                            g[f"{side}_bytes"][
                                int(g[f"{side}_offset"][row]) : int(g[f"{side}_offset"][row])
                                + int(g[f"{side}_length"][row])
                            ].tobytes()
                        )
                        == int(g[f"{side}_xxh3_64"][row])
                        for side in ("left", "right")
                    )
            except (KeyError, OSError):
                ok = 0
            out[int(name)] = ok
    return out


def test_reading_a_changed_image_names_its_camera_row_and_side(clean, tmp_path):
    path = tmp_path / "s.h5"
    shutil.copy(clean, path)
    _flip_image_byte(path, 101, 7, "left")
    with SessionReader(path) as r:
        with pytest.raises(ImageChecksumError) as caught:
            r.frame_bytes(101, 7)
        assert (caught.value.camera_serial, caught.value.row, caught.value.side) == (101, 7, "left")
        assert "camera 101 row 7 left image does not match its recorded checksum" in str(
            caught.value
        )
        assert isinstance(caught.value, SessionFormatError)  # refused by default, one line
        assert r.image_bytes(101, 7, "right")  # the other side is intact and readable
        for row in (6, 8):
            r.frame_bytes(101, row)


@pytest.mark.timeout(120)
def test_export_frames_skips_a_damaged_image_writes_the_rest_and_lists_it(clean, tmp_path):
    path = tmp_path / "s.h5"
    shutil.copy(clean, path)
    _flip_image_byte(path, 103, 12, "right")  # camera 103 records raw images: all decodable
    out = tmp_path / "png"
    done = run_egosurg(
        "session", "export-frames", str(path), "--out", str(out), "--camera", "103", timeout=60
    )
    assert done.returncode == 1, (done.stdout, done.stderr)
    assert "Traceback" not in done.stderr
    assert "SN103 row 12 right" in done.stderr and "checksum" in done.stderr
    assert "wrote 119 PNG(s)" in done.stdout  # 60 sets x 2 sides, less the damaged one
    assert not (out / "set_000012" / "SN103_right.png").exists()
    assert (out / "set_000012" / "SN103_left.png").exists()


def _heap_damaged(path: Path) -> None:
    data = bytearray(path.read_bytes())
    _zeroed_string_header(data)  # every string attribute: HDF5 loops on the heap
    path.write_bytes(bytes(data))


def _bad_root_values(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        f.attrs["format"] = "egosurg-sessiqn"  # one changed letter
        f.attrs["case_metadata_json"] = '{"room": ["not", "text"]'
        del f.attrs["tolerance_ns"]


@pytest.mark.timeout(120)
@pytest.mark.parametrize("damage", [_heap_damaged, _bad_root_values])
def test_recover_saves_every_intact_frame_when_the_root_attributes_are_damaged(
    clean, tmp_path, monkeypatch, damage
):
    from protocol.session import probe, salvage

    monkeypatch.setattr(probe, "PROBE_STALL_S", 3.0)  # the defaults are 10 s
    monkeypatch.setattr(salvage, "SALVAGE_STALL_S", 3.0)
    path = tmp_path / "root.h5"
    shutil.copy(clean, path)
    damage(path)
    with pytest.raises(SessionFormatError):
        SessionReader(path)  # the reader refuses it as it is
    assert _h5py_intact(path) == INTACT
    report = recover_session(path, tmp_path / "r.h5")
    assert report.frames_kept == _h5py_intact(path)
    assert report.sets_kept == 60 and report.gaps_kept == 4
    assert any("rebuilt" in p for p in report.problems), report.problems
    with SessionReader(tmp_path / "r.h5") as r:
        assert r.verify() == []
        assert r.info.camera_serials == (101, 102, 103)
        assert r.info.camera(103).encoding == "raw_bgr8" and r.info.camera(101).width == 1920
        assert r.summary()["extra"]["recovered_from"]["problems"] == report.problems


@pytest.mark.timeout(120)
def test_recover_loses_only_the_camera_whose_header_is_damaged(clean, tmp_path):
    path = tmp_path / "cam.h5"
    shutil.copy(clean, path)
    with h5py.File(path, "r") as f:
        header = h5py.h5o.get_info(f["cameras/102"].id).addr
    with open(path, "r+b") as f:  # a byte inside camera 102's object header: its checksum fails
        f.seek(header + 40)
        byte = f.read(1)[0]
        f.seek(header + 40)
        f.write(bytes([byte ^ 0xFF]))
    with pytest.raises(SessionFormatError):
        SessionReader(path)
    assert _h5py_intact(path) == {101: 60, 102: 0, 103: 60}
    target = tmp_path / "r.h5"
    done = run_egosurg("session", "recover", str(path), "--out", str(target), timeout=60)
    assert done.returncode == 0, (done.stdout, done.stderr)
    assert "camera 101: 60 frames kept, 0 lost" in done.stdout
    assert "camera 103: 60 frames kept, 0 lost" in done.stdout
    assert "camera 102: 0 frames kept, all lost" in done.stdout
    assert "/cameras/102 cannot be read" in done.stdout  # what was skipped, and why
    assert "synchronised sets: 60 kept, 0 lost" in done.stdout
    with SessionReader(target) as r:
        assert r.verify() == []
        assert r.info.camera_serials == (101, 103)
        members = r.sets().members
        assert members.shape == (60, 2) and np.array_equal(members[:, 0], np.arange(60))
        with h5py.File(path, "r") as f:  # the bytes are those of the damaged file
            g = f["cameras/101"]
            off, n = int(g["left_offset"][5]), int(g["left_length"][5])
            assert r.frame_bytes(101, 5)[0] == g["left_bytes"][off : off + n].tobytes()


def test_recover_keeps_a_set_whose_one_member_is_damaged_without_that_member(clean, tmp_path):
    path = tmp_path / "s.h5"
    shutil.copy(clean, path)
    _flip_image_byte(path, 101, 7, "left")
    report = recover_session(path, tmp_path / "r.h5")
    assert report.frames_kept == {101: 59, 102: 51, 103: 60} == _h5py_intact(path)
    assert report.sets_kept == 60
    assert "1 set members whose frames were not kept are left out of their sets" in report.problems
    with SessionReader(tmp_path / "r.h5") as r:
        assert r.verify() == []
        members = r.sets().members
        assert members[7, 0] == -1 and members[7, 2] == 7  # set 7 keeps cameras 102 and 103
        assert members[8, 0] == 7  # camera 101's later frames moved up one row


def test_recover_keeps_the_session_events(tmp_path):
    from tests.protocol.test_session import _append, _cameras, _image, _writer

    path = tmp_path / "events.h5"
    with _writer(path, _cameras(11)) as w:
        for row in range(5):
            _append(w, 11, row, (_image(11, row, 0), _image(11, row, 1)))
        w.append_event(1, time_unix_ns=5, node_id="orin-a", detail="link dropped")
        w.append_event(3, time_unix_ns=6, node_id="orin-a", camera_serial=11, count=2)
        w.close(10, {})
    report = recover_session(path, tmp_path / "r.h5")
    assert (report.events_kept, report.events_lost) == (2, 0)
    with SessionReader(path) as before, SessionReader(tmp_path / "r.h5") as after:
        assert after.events() == before.events() and after.verify() == []
