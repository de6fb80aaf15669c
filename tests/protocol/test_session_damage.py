"""A session is a medical record: damaged files give one clear error, never a hang or a traceback;
changed image bytes are caught by their checksums; what is intact can be recovered; files are
owner-only and hold no keys; a recorder killed mid-take resumes the case into a linked file.

Real files (written by ``SessionWriter``, damaged with plain file writes), real processes
(a writer and a recorder killed with SIGKILL), the real ``egosurg`` command."""

from __future__ import annotations

import os
import random
import re
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import zmq

from protocol.session import SessionFormatError, SessionReader, SessionWriter
from protocol.session.privacy import make_private_dir
from protocol.session.recover import recover_session
from tests.conftest import REPO, run_egosurg
from tests.protocol.test_session import _append, _cameras, _image, _write_session, _writer

CUTS = [512, 4096, 65_536, 300_000, 1 << 20]


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("damage") / "clean.h5"
    _write_session(path, rows=60)
    return path


KILLED_WRITER = """
import sys, time
sys.path.insert(0, {repo!r})
from tests.protocol.test_session import _append, _cameras, _image, _writer, T0_NS, PERIOD_NS
w = _writer({path!r}, _cameras(11, 12))
for row in range({rows}):
    for serial in (11, 12):
        _append(w, serial, row, (_image(serial, row, 0), _image(serial, row, 1)))
    spread = abs((T0_NS + row * PERIOD_NS + 11) - (T0_NS + row * PERIOD_NS + 12))
    w.append_set(T0_NS + row * PERIOD_NS, [row, row], spread)
    if row % 10 == 9:
        w.flush()
print("flushed", flush=True)
time.sleep(120)
"""


@pytest.fixture(scope="module")
def killed(tmp_path_factory) -> Path:
    """A writer SIGKILLed after flushing 40 frames per camera and 40 sets (5 more unflushed)."""
    path = tmp_path_factory.mktemp("killed") / "killed.h5"
    code = KILLED_WRITER.format(repo=str(REPO), path=str(path), rows=45)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "flushed"
    finally:
        proc.kill()
        proc.wait(timeout=30)
    return path


def _read_everything(path: Path) -> list[str]:
    with SessionReader(path) as r:
        r.sets(), r.gaps(), r.summary()
        for serial in r.info.camera_serials:
            r.frame_table(serial)
            for row in range(r.frame_count(serial)):
                r.frame_bytes(serial, row)
        return r.verify()


def _copy_cut(src: Path, dst: Path, cut: int) -> Path:
    shutil.copy(src, dst)
    os.truncate(dst, dst.stat().st_size - cut)
    return dst


@pytest.mark.timeout(60)
@pytest.mark.parametrize("cut", CUTS)
def test_a_truncated_file_is_refused_at_once_with_what_is_missing(clean, tmp_path, cut):
    path = _copy_cut(clean, tmp_path / "cut.h5", cut)
    with pytest.raises(SessionFormatError, match=rf"truncated.*\({cut} bytes missing"):
        SessionReader(path)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("cut", CUTS)
def test_a_killed_writers_file_truncated_fails_clearly_not_forever(killed, tmp_path, cut):
    """A killed writer's superblock records an early end of file, so the cut is found by HDF5's
    metadata checksums, which must fail after a bounded number of tries (no SWMR retry hang)."""
    path = _copy_cut(killed, tmp_path / "cut.h5", cut)
    with pytest.raises(SessionFormatError, match=r"cut\.h5"):
        _read_everything(path)


@pytest.mark.timeout(120)
def test_the_session_commands_give_one_line_and_exit_2_on_a_truncated_file(clean, tmp_path):
    path = _copy_cut(clean, tmp_path / "cut.h5", 1 << 20)
    for args in (["info"], ["verify"], ["export-frames", "--out", str(tmp_path / "png")]):
        out = run_egosurg("session", args[0], str(path), *args[1:], timeout=60)
        assert out.returncode == 2, (args, out.stdout, out.stderr)
        assert "Traceback" not in out.stderr and "truncated" in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr


@pytest.mark.timeout(60)
@pytest.mark.parametrize("size", [1, 8, 9, 12, 20, 40, 100])
def test_a_file_cut_inside_its_superblock_is_refused_with_a_format_error(clean, tmp_path, size):
    """A copy cut to its first bytes (the signature and a little more; found by the fuzzer at
    9 bytes, which raised IndexError): one SessionFormatError at once, and exit 2 at the CLI."""
    path = tmp_path / "short.h5"
    path.write_bytes(clean.read_bytes()[:size])
    words = r"short\.h5: (not an HDF5 file|the HDF5 superblock is cut short|truncated)"
    with pytest.raises(SessionFormatError, match=words):
        SessionReader(path)
    if size == 9:
        out = run_egosurg("session", "info", str(path), timeout=60)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        assert "superblock is cut short" in out.stderr


def _global_heap(data: bytes) -> tuple[int, list[tuple[int, int, int]]]:
    """The first global heap collection in ``data`` (HDF5 file format spec, "Global Heap"): its
    offset and its objects as (offset of the object header, heap index, object size)."""
    at = data.index(b"GCOL")
    assert data[at + 4] == 1  # collection version 1
    end = at + int.from_bytes(data[at + 8 : at + 16], "little")
    objects, p = [], at + 16
    while p + 16 <= end:
        index = int.from_bytes(data[p : p + 2], "little")
        size = int.from_bytes(data[p + 8 : p + 16], "little")
        objects.append((p, index, size))
        if index == 0:  # the free space: the rest of the collection
            break
        p += 16 + (size + 7) // 8 * 8
    return at, objects


def _shrunk_free_space_landing(data: bytearray) -> None:
    """The last string's length field changed so the next object header is read from zeros
    inside the free space (index 0, size 0): the parser never moves on."""
    _, objects = _global_heap(bytes(data))
    (last_at, index, _), (free_at, free_index, free_size) = objects[-2], objects[-1]
    assert index > 0 and free_index == 0 and free_size >= 64, objects[-3:]
    size = free_at + 32 - last_at - 16
    data[last_at + 8 : last_at + 16] = size.to_bytes(8, "little")


def _zeroed_string_header(data: bytearray) -> None:
    """A range of zeros over the first string's header (the fuzzer zeroed 1,884 bytes there)."""
    _, objects = _global_heap(bytes(data))
    first_at = objects[0][0]
    data[first_at : first_at + 16] = bytes(16)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("damage", [_shrunk_free_space_landing, _zeroed_string_header])
def test_a_damaged_string_heap_is_refused_without_hanging(clean, tmp_path, monkeypatch, damage):
    """Damage in HDF5's global heap (the string attributes; no checksum) made HDF5 loop forever
    inside the first attribute read. The reader's first open reads the metadata in a child with
    a time limit, so the file is refused with a clear error and the caller never hangs; recover
    salvages its frames, bounded in time too (tests/protocol/test_session_integrity.py)."""
    from protocol.session import probe as session_probe
    from protocol.session import salvage

    monkeypatch.setattr(session_probe, "PROBE_STALL_S", 3.0)  # the default is 10 s
    monkeypatch.setattr(salvage, "SALVAGE_STALL_S", 3.0)
    data = bytearray(clean.read_bytes())
    damage(data)
    path = tmp_path / "heap.h5"
    path.write_bytes(bytes(data))
    with pytest.raises(SessionFormatError, match=r"heap\.h5: the file's metadata is damaged"):
        SessionReader(path)
    report = recover_session(path, tmp_path / "recovered.h5")
    assert report.frames_kept == {101: 60, 102: 51, 103: 60} and report.sets_kept == 60


@pytest.mark.timeout(60)
def test_a_damaged_string_heap_is_refused_too_while_other_threads_run(clean, tmp_path, monkeypatch):
    """With other threads running the probe is a new interpreter, not a fork (a fork could copy
    a lock another thread holds): the same refusal, and a healthy file still opens."""
    from protocol.session import probe as session_probe

    monkeypatch.setattr(session_probe, "PROBE_STALL_S", 3.0)
    data = bytearray(clean.read_bytes())
    _zeroed_string_header(data)
    path = tmp_path / "heap.h5"
    path.write_bytes(bytes(data))
    healthy = shutil.copy(clean, tmp_path / "healthy.h5")
    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    other.start()
    try:
        with pytest.raises(SessionFormatError, match=r"heap\.h5: the file's metadata is damaged"):
            SessionReader(path)
        with SessionReader(healthy) as reader:
            assert reader.info.session_name
    finally:
        stop.set()
        other.join(timeout=10)


def _metadata_positions(path: Path, k: int, seed: int) -> list[int]:
    """``k`` positions of non-zero bytes outside every image chunk: metadata and tables."""
    data = np.fromfile(path, dtype=np.uint8)
    mask = data != 0
    with h5py.File(path, "r", swmr=True) as f:
        for serial in f["cameras"]:
            for side in ("left", "right"):
                ds = f[f"cameras/{serial}/{side}_bytes"]
                for i in range(ds.id.get_num_chunks()):
                    info = ds.id.get_chunk_info(i)
                    mask[info.byte_offset : info.byte_offset + info.size] = False
    return random.Random(seed).sample(np.flatnonzero(mask).tolist(), k)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("name", ["clean", "killed"])
def test_flipped_bytes_in_metadata_give_a_clear_error_or_a_readable_file(request, tmp_path, name):
    """Any damage to metadata: the reader either still reads the file or says it is damaged;
    it never raises anything but SessionFormatError and never hangs (the test's timeout)."""
    source = request.getfixturevalue(name)
    outcomes = {"read": 0, "refused": 0}
    for k, pos in enumerate(_metadata_positions(source, 40, seed=24)):
        path = tmp_path / f"flip{k}.h5"
        shutil.copy(source, path)
        with open(path, "r+b") as f:
            f.seek(pos)
            byte = f.read(1)[0]
            f.seek(pos)
            f.write(bytes([byte ^ (1 << (k % 8))]))
        try:
            _read_everything(path)
            outcomes["read"] += 1
        except SessionFormatError:
            outcomes["refused"] += 1
        path.unlink()
    assert outcomes["refused"] > 0, outcomes  # flipped metadata is noticed, not ignored
    print(f"\n{name}: 40 single-bit flips in metadata -> {outcomes}")


def test_a_changed_image_byte_is_reported_with_its_camera_row_and_side(clean, tmp_path):
    path = tmp_path / "s.h5"
    shutil.copy(clean, path)
    with h5py.File(path, "r+") as f:
        off, n = int(f["cameras/101/left_offset"][7]), int(f["cameras/101/left_length"][7])
        blob = f["cameras/101/left_bytes"]
        blob[off + n // 2] = blob[off + n // 2] ^ 0x01  # markers intact: only a checksum sees it
        off = int(f["cameras/103/right_offset"][12])  # a raw image, its size unchanged
        f["cameras/103/right_bytes"][off] ^= 0x80
    with SessionReader(path) as r:
        problems = r.verify()
        quick = r.verify(check_images=False)
    assert [p for p in problems if "checksum" in p] == [
        "error: camera 101: left images of rows 7 do not match their checksums (xxh3_64): "
        "their bytes changed after they were recorded",
        "error: camera 103: right images of rows 12 do not match their checksums (xxh3_64): "
        "their bytes changed after they were recorded",
    ], problems
    assert quick == []  # --quick reads no image
    out = run_egosurg("session", "verify", str(path), timeout=60)
    assert out.returncode == 1 and "left images of rows 7" in out.stdout, out


def test_a_version_1_file_without_checksums_is_read_and_says_so(clean, tmp_path):
    """Files recorded before the checksums (format_version 1) stay readable."""
    path = tmp_path / "v1.h5"
    shutil.copy(clean, path)
    with h5py.File(path, "r+") as f:  # what the version-1 writer wrote
        f.attrs["format_version"] = 1
        for serial in f["cameras"]:
            for side in ("left", "right"):
                del f[f"cameras/{serial}/{side}_xxh3_64"]
        del f.attrs["previous_session_file"], f.attrs["take_part"]
    with SessionReader(path) as r:
        assert r.info.format_version == 1 and not r.info.has_checksums
        assert "left_xxh3_64" not in r.frame_table(101) and r.frame_count(101) == 60
        assert r.info.take_part == 1 and r.info.previous_session_file == ""
        assert r.verify() == [
            "note: no checksums (format version 1): images are checked for their JPEG markers "
            "and sizes only"
        ]


def _reshape(f: h5py.File) -> None:
    del f["cameras/101/seq"]
    f["cameras/101/seq"] = np.zeros((60, 2), dtype=np.int64)


def _flatten_members(f: h5py.File) -> None:
    del f["sets/members"]
    f["sets/members"] = np.zeros(60, dtype=np.int64)


def _float_bytes(f: h5py.File) -> None:
    del f["cameras/102/right_bytes"]
    f["cameras/102/right_bytes"] = np.zeros(10, dtype=np.float64)


def _bad_metadata(f: h5py.File) -> None:
    f.attrs["case_metadata_json"] = '{"room": ["not", "text"]'


def _drop_group(f: h5py.File) -> None:
    del f["cameras/103"]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (_reshape, "cameras/101/seq has shape (60, 2)"),
        (_flatten_members, "sets/members has shape (60,)"),
        (_float_bytes, "cameras/102/right_bytes is missing or not a 1-D byte dataset"),
        (_bad_metadata, "missing or bad part"),
        (_drop_group, "missing or bad part"),
    ],
)
def test_a_wrong_layout_is_refused_when_the_file_opens(clean, tmp_path, damage, words):
    path = tmp_path / "s.h5"
    shutil.copy(clean, path)
    with h5py.File(path, "r+") as f:
        damage(f)
    with pytest.raises(SessionFormatError, match=re.escape(words)):
        SessionReader(path)
    out = run_egosurg("session", "info", str(path), timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out


@pytest.mark.timeout(60)
def test_bad_summary_json_is_a_format_error_and_exit_2(clean, tmp_path):
    path = tmp_path / "s.h5"
    shutil.copy(clean, path)
    with h5py.File(path, "r+") as f:
        f["summary"].attrs["summary_json"] = "{not json"
    with SessionReader(path) as r, pytest.raises(SessionFormatError, match="/summary"):
        r.summary()
    out = run_egosurg("session", "verify", str(path), timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr and "/summary" in out.stderr


@pytest.mark.timeout(120)
def test_recover_keeps_every_flushed_frame_and_set_of_a_killed_writer(killed, tmp_path):
    target = tmp_path / "recovered.h5"
    out = run_egosurg("session", "recover", str(killed), "--out", str(target), timeout=60)
    assert out.returncode == 0, out
    assert "camera 11: 40 frames kept, 0 lost" in out.stdout
    assert "synchronised sets: 40 kept, 0 lost" in out.stdout
    with SessionReader(target) as r:
        assert r.info.closed_cleanly and r.verify() == []
        assert r.sets().members.tolist() == [[k, k] for k in range(40)]
        for serial in (11, 12):
            for row in range(40):
                assert r.frame_bytes(serial, row) == (
                    _image(serial, row, 0),
                    _image(serial, row, 1),
                )
        assert r.summary()["extra"]["recovered_from"]["source"] == str(killed)
    assert stat.S_IMODE(target.stat().st_mode) == 0o600


@pytest.mark.timeout(120)
def test_recover_a_truncated_copy_and_refuse_what_is_not_hdf5(clean, tmp_path):
    """The last 512 bytes of a closed file are unused image capacity: every frame survives."""
    source = _copy_cut(clean, tmp_path / "cut.h5", 512)
    report = recover_session(source, tmp_path / "r.h5")
    assert report.frames_kept == {101: 60, 102: 51, 103: 60} and report.sets_kept == 60
    with SessionReader(tmp_path / "r.h5") as r:
        assert r.verify() == []
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(300))
    out = run_egosurg("session", "recover", str(junk), "--out", str(tmp_path / "x.h5"))
    assert out.returncode == 2 and "nothing can be recovered" in out.stderr, out
    assert not (tmp_path / "x.h5").exists()


def test_session_files_are_0600_and_the_folder_0700_whatever_the_umask(tmp_path):
    folder = tmp_path / "sessions"
    folder.mkdir(mode=0o755)
    old = os.umask(0o022)
    try:
        assert make_private_dir(folder) == folder
        with _writer(folder / "s.h5", _cameras(1)) as w:
            _append(w, 1, 0, (_image(1, 0, 0), _image(1, 0, 1)))
    finally:
        os.umask(old)
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert stat.S_IMODE((folder / "s.h5").stat().st_mode) == 0o600


def test_a_rig_config_with_an_inline_secret_key_is_not_stored_verbatim(tmp_path):
    secret = zmq.curve_keypair()[1].decode()
    text = (
        'rig_name = "or3"\n[security]\n'
        'secret_key = "/etc/egosurg/keys/recorder.key_secret"\n'
        f'operator_key = "{secret}"\npassword = "hunter2"\n'
        f'inline = """\n{secret}\n"""\n'
    )
    for k, body in enumerate((text, text.split("inline")[0])):
        path = tmp_path / f"s{k}.h5"
        SessionWriter(
            path,
            session_name="s",
            case_metadata={},
            cameras=_cameras(1),
            tolerance_ns=1000,
            rig_config_text=body,
            software_version="test",
            started_unix_ns=1,
        ).close(1)
        with SessionReader(path) as r:
            stored = r.info.rig_config_toml
        assert secret not in stored and "hunter2" not in stored, stored
        if k == 1:  # one-line values are removed, the key file's path kept
            assert (
                "/etc/egosurg/keys/recorder.key_secret" in stored and 'rig_name = "or3"' in stored
            )
        else:  # a multi-line secret cannot be cut out safely: nothing of the text is stored
            assert stored.startswith("# the rig configuration was not stored")


@pytest.mark.timeout(300)
def test_a_recorder_killed_mid_take_resumes_into_a_linked_file(tmp_path):
    from sim.deploy import SimRig, SimRigSpec, write_sim_rig

    files = write_sim_rig(
        tmp_path / "rig",
        SimRigSpec(
            seed=2,
            cameras=2,
            fps=15.0,
            prerender_s=1.0,
            drop_probability=0.0,
            plaintext=True,  # the take under test; sealed ones: tests/e2e/test_sealed_session.py
        ),
    )
    with SimRig(files) as rig:
        rig.wait_streaming(timeout_s=240)
        first = Path(rig.control("start", case="resume-me", meta={"room": "OR 3"})["file"])
        time.sleep(2.5)  # several flushes (every 0.5 s)
        rig.signal("recorder", signal.SIGKILL)
        rig.start_recorder()
        deadline = time.monotonic() + 120
        status: dict = {}
        while time.monotonic() < deadline:
            try:
                status = rig.control("status", timeout_s=2.0)
            except Exception:  # the new recorder is still starting
                time.sleep(0.3)
                continue
            if status.get("recording"):
                break
            time.sleep(0.3)
        assert status.get("recording"), status
        assert status["take_resume"]["state"] == "resumed", status
        time.sleep(1.5)
        summary = rig.control("stop")
    second = Path(summary["file"])
    assert second != first and not (files.session_dir / "take-journal.json").exists()
    with SessionReader(second) as r:
        assert r.info.previous_session_file == first.name and r.info.take_part == 2
        assert r.info.case_metadata == {"room": "OR 3", **files.sim_metadata()}
        assert r.info.session_name == "resume-me"
        assert len(r.sets().set_unix_ns) > 0 and r.verify() == []
    with SessionReader(first) as r:  # the killed part: every flushed set intact
        assert not r.info.closed_cleanly
        assert len(r.sets().set_unix_ns) >= 10
        assert all(p.startswith("note: ") for p in r.verify()), r.verify()
    out = run_egosurg("session", "info", str(second), timeout=60)
    assert f"take part 2: continues {first.name}" in out.stdout, out
