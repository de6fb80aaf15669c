"""The HDF5 session file: real files, real h5py edits, a real writer killed with SIGKILL."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from protocol.errors import UserError
from protocol.session import (
    FRAME_COLUMNS,
    CameraInfo,
    GapKind,
    GapRecord,
    SessionFormatError,
    SessionNotFoundError,
    SessionReader,
    SessionWriteError,
    SessionWriter,
)

REPO = Path(__file__).resolve().parents[2]
T0_NS = 1_770_000_000_000_000_000
PERIOD_NS = 33_333_333
_NOISE = (np.arange(1 << 20, dtype=np.uint64) * 2654435761 % 251).astype(np.uint8).tobytes()


def _image(serial: int, row: int, side: int) -> bytes:
    """A deterministic fake JPEG: SOI marker, payload that depends on every argument, EOI."""
    size = 8_000 + (row * 7_919 + serial * 31 + side * 4_001) % 60_000
    start = (row * 131 + serial + side * 977) % (len(_NOISE) - size)
    head = b"\xff\xd8" + f"{serial}/{row}/{side}".encode()
    return head + _NOISE[start : start + size] + b"\xff\xd9"


def _raw(row: int, width: int = 8, height: int = 4) -> bytes:
    return bytes((row + i) % 256 for i in range(width * height * 3))


def _cameras(*serials: int, raw: int | None = None) -> list[CameraInfo]:
    return [
        CameraInfo(
            camera_serial=s,
            node_id=f"node{i // 2}",
            resolution="HD1200" if s != raw else "TINY",
            width=1920 if s != raw else 8,
            height=1200 if s != raw else 4,
            fps_nominal=30.0,
            encoding="jpeg" if s != raw else "raw_bgr8",
            factory_conf_text=f"[STEREO]\nBaseline=119.{i}\n" if i % 2 == 0 else "",
        )
        for i, s in enumerate(serials)
    ]


def _writer(path: Path, cameras: list[CameraInfo], **options: Any) -> SessionWriter:
    return SessionWriter(
        path,
        session_name="case-042",
        case_metadata={"procedure": "laparoscopic cholecystectomy", "room": "OR 3", "é": "ü"},
        cameras=cameras,
        tolerance_ns=PERIOD_NS // 2,
        rig_config_text='[rig]\nname = "or3"\n',
        software_version="0.1.0",
        started_unix_ns=T0_NS,
        **options,
    )


def _append(w: SessionWriter, serial: int, row: int, data: tuple[Any, Any]) -> int:
    return w.append_frame(
        serial,
        left=data[0],
        right=data[1],
        capture_unix_ns=T0_NS + row * PERIOD_NS + serial % 1000,
        host_receive_unix_ns=T0_NS + row * PERIOD_NS + 2_000_000,
        recorder_receive_unix_ns=T0_NS + row * PERIOD_NS + 3_000_000,
        frame_index=row + (5 if row >= 10 and serial == 101 else 0),
        seq=row * 3 + serial % 7,
        ptp_offset_ns=-120 + row,
        ptp_locked=row % 9 != 8,
    )


def _write_session(path: Path, rows: int = 30) -> dict:
    """Three cameras (one raw), sets with missing members, gaps of every kind, a clean close."""
    cameras = _cameras(101, 102, 103, raw=103)
    expected: dict = {"frames": {101: [], 102: [], 103: []}, "sets": [], "gaps": []}
    with _writer(path, cameras) as w:
        for row in range(rows):
            for serial in (101, 102, 103):
                if serial == 102 and row % 7 == 3:
                    continue  # camera 102 misses some sets
                if serial == 103:
                    data = (_raw(row), _raw(row + 1))
                else:
                    data = (_image(serial, row, 0), _image(serial, row, 1))
                r = _append(w, serial, row, data)
                assert r == len(expected["frames"][serial])
                expected["frames"][serial].append(data)
            members = [row, -1 if row % 7 == 3 else row - (row + 3) // 7, row]
            times = [
                T0_NS + row * PERIOD_NS + s % 1000
                for s, m in zip((101, 102, 103), members, strict=True)
                if m >= 0
            ]
            spread = max(times) - min(times)
            w.append_set(T0_NS + row * PERIOD_NS, members, spread)
            expected["sets"].append((T0_NS + row * PERIOD_NS, members, spread))
            if row % 10 == 9:
                w.flush()
        for kind in GapKind:
            gap = GapRecord(
                camera_serial=101 if kind != GapKind.SEQ_GAP else 102,
                kind=kind,
                first_missing_frame_index=10 + kind,
                missing_count=5 if kind != GapKind.RECONNECT else -1,
                start_unix_ns=T0_NS + kind * PERIOD_NS,
                end_unix_ns=T0_NS + (kind + 6) * PERIOD_NS,
            )
            w.append_gap(
                gap.camera_serial,
                kind=gap.kind,
                first_missing_frame_index=gap.first_missing_frame_index,
                missing_count=gap.missing_count,
                start_unix_ns=gap.start_unix_ns,
                end_unix_ns=gap.end_unix_ns,
            )
            expected["gaps"].append(gap)
        assert w.frames_written(101) == rows
        assert w.bytes_written == sum(
            len(a) + len(b) for frames in expected["frames"].values() for a, b in frames
        )
        w.close(T0_NS + rows * PERIOD_NS, {"rejected_messages": np.int64(0), "fps": {"101": 29.97}})
    return expected


@pytest.fixture
def session(tmp_path: Path) -> tuple[Path, dict]:
    path = tmp_path / "case-042.h5"
    return path, _write_session(path)


def test_round_trip_keeps_every_byte_and_field(session):
    path, expected = session
    with SessionReader(path) as r:
        info = r.info
        assert info.session_name == "case-042"
        assert info.case_metadata["é"] == "ü"
        assert info.closed_cleanly and info.stopped_unix_ns == T0_NS + 30 * PERIOD_NS
        assert info.started_unix_ns == T0_NS and info.tolerance_ns == PERIOD_NS // 2
        assert info.camera_serials == (101, 102, 103)
        assert info.cameras == tuple(_cameras(101, 102, 103, raw=103))
        assert info.rig_config_toml.startswith("[rig]")
        for serial, frames in expected["frames"].items():
            assert r.frame_count(serial) == len(frames)
            table = r.frame_table(serial)
            assert set(table) == set(FRAME_COLUMNS)
            assert np.all(np.diff(table["capture_unix_ns"]) > 0)
            for row, data in enumerate(frames):
                assert r.frame_bytes(serial, row) == data
        t101 = r.frame_table(101)
        assert t101["frame_index"][12] == 17 and t101["ptp_locked"][8] == 0
        assert t101["seq"][4] == 4 * 3 + 101 % 7 and t101["ptp_offset_ns"][0] == -120
        sets = r.sets()
        assert sets.members.shape == (30, 3)
        assert sets.members.tolist() == [m for _, m, _ in expected["sets"]]
        assert sets.set_unix_ns.tolist() == [t for t, _, _ in expected["sets"]]
        assert sets.spread_ns.tolist() == [s for _, _, s in expected["sets"]]
        assert (sets.members == -1).sum() == 4  # explicit markers, no silent shift
        assert r.gaps() == expected["gaps"]
        summary = r.summary()
        assert summary["101"]["frames"] == 30 and summary["102"]["frames"] == 26
        assert summary["101"]["missing_frames"] == 5 and summary["102"]["missing_frames"] == 5
        assert summary["101"]["gap_records"] == 3
        assert summary["extra"] == {"fps": {"101": 29.97}, "rejected_messages": 0}
        assert r.verify() == []
        with pytest.raises(IndexError):
            r.frame_bytes(101, 30)
    with h5py.File(path, "r") as f:  # plain h5py, as docs/session.md describes
        assert f.attrs["format"] == "egosurg-session" and f.attrs["format_version"] == 2
        assert f["cameras/101/left_bytes"].shape[0] == sum(
            len(a) for a, _ in expected["frames"][101]
        )
        off, n = f["cameras/102/right_offset"][5], f["cameras/102/right_length"][5]
        assert (
            f["cameras/102/right_bytes"][off : off + n].tobytes() == expected["frames"][102][5][1]
        )


def test_any_bytes_like_image_is_stored_as_is(tmp_path):
    path = tmp_path / "s.h5"
    data = _image(7, 0, 0)
    inputs = [data, bytearray(data), memoryview(data), np.frombuffer(data, dtype=np.uint8)]
    with _writer(path, _cameras(7)) as w:
        for row, item in enumerate(inputs):
            _append(w, 7, row, (item, item))
        w.append_set(T0_NS, [0], 0)
    with SessionReader(path) as r:
        assert all(r.frame_bytes(7, row) == (data, data) for row in range(len(inputs)))
        assert r.verify() == []


def test_images_across_chunks_and_flushes_mid_chunk(tmp_path):
    """Small chunks, so images span several of them and flushes land mid-chunk: every flush
    shows exactly the bytes appended, the tail of the capacity is zeros, and a clean close
    trims it."""
    path = tmp_path / "chunks.h5"
    chunk = 4096
    sizes = [1, 4095, 4096, 4097, 3 * 4096 + 17, 12, 2 * 4096, 9_000, 5, 4096 * 7 - 3]
    rng = np.random.default_rng(7)
    images = [
        b"\xff\xd8" + rng.integers(0, 256, n, dtype=np.uint8).tobytes() + b"\xff\xd9" for n in sizes
    ]
    with _writer(path, _cameras(1, 2), blob_chunk_bytes=chunk) as w:
        for row, image in enumerate(images):
            _append(w, 1, row, (image, images[-1 - row]))
            _append(w, 2, row, (images[-1 - row], image))
            if row % 3 == 1:
                w.flush()
                with SessionReader(path) as r:  # a reader of the live file
                    assert r.frame_count(1) == row + 1
                    for k in range(row + 1):
                        assert r.frame_bytes(1, k) == (images[k], images[-1 - k])
                    end = int(r.frame_table(1)["left_offset"][row]) + len(image)
                    with h5py.File(path, "r", swmr=True) as f:
                        ds = f["cameras/1/left_bytes"]
                        assert ds.chunks == (chunk,) and ds.shape[0] % chunk == 0
                        assert not ds[end:].any()  # the capacity's tail: zeros
    with SessionReader(path) as r:
        assert r.verify() == []
        for row, image in enumerate(images):
            assert r.frame_bytes(1, row) == (image, images[-1 - row])
            assert r.frame_bytes(2, row) == (images[-1 - row], image)
    with h5py.File(path, "r") as f:
        total = sum(len(i) for i in images)
        assert f["cameras/1/left_bytes"].shape == (total,)
        assert f["cameras/1/left_bytes"][:].tobytes() == b"".join(images)


def test_a_failed_write_loses_nothing_and_is_reported_before_more_is_recorded(
    tmp_path, monkeypatch
):
    """Disk full while chunks are queued: the flush says so, appends are refused before they
    change anything until a flush succeeds, and once there is room again every frame is in the
    file, the frames whose chunks failed included."""
    from protocol.session import chunk_sink

    path = tmp_path / "s.h5"
    real = chunk_sink._pwrite
    full = threading.Event()

    def pwrite(fd: int, data: Any, offset: int) -> int:
        if full.is_set():
            raise OSError(28, "No space left on device")
        return real(fd, data, offset)

    monkeypatch.setattr(chunk_sink, "_pwrite", pwrite)
    frames = [(_image(1, row, 0), _image(1, row, 1)) for row in range(8)]
    with _writer(path, _cameras(1), blob_chunk_bytes=4096) as w:
        for row in range(3):
            assert _append(w, 1, row, frames[row]) == row
        w.flush()
        full.set()
        assert _append(w, 1, 3, frames[3]) == 3  # its chunks fail in the writer's thread
        with pytest.raises(SessionWriteError, match="No space left"):
            w.flush()
        with pytest.raises(SessionWriteError, match="check free disk space"):
            _append(w, 1, 4, frames[4])
        with SessionReader(path) as r:  # the file as a crash now would leave it
            assert r.frame_count(1) == 3
            assert [r.frame_bytes(1, row) for row in range(3)] == frames[:3]
        full.clear()
        w.flush()  # the failed chunks are written now; appends are taken again
        for row in range(4, 8):
            assert _append(w, 1, row, frames[row]) == row
    with SessionReader(path) as r:
        assert r.verify() == []
        assert [r.frame_bytes(1, row) for row in range(8)] == frames


@pytest.mark.parametrize("direct_io", [None, True, False])
def test_the_bytes_are_the_same_with_and_without_direct_io(tmp_path, direct_io):
    """Direct I/O (required, or where the file system takes it) and writes through the page
    cache store the same bytes, read back through the cache by a live reader and after close."""
    path = tmp_path / "s.h5"
    frames = [(_image(5, row, 0), _image(5, row, 1)) for row in range(40)]
    try:
        w = _writer(path, _cameras(5), direct_io=direct_io)
    except OSError as exc:  # only where direct I/O is required and this file system refuses it
        assert direct_io is True
        pytest.skip(f"no direct I/O on {tmp_path}: {exc}")
    with w:
        for row, data in enumerate(frames):
            _append(w, 5, row, data)
            if row % 9 == 4:
                w.flush()
                with SessionReader(path) as r:
                    assert [r.frame_bytes(5, k) for k in range(row + 1)] == frames[: row + 1]
    with SessionReader(path) as r:
        assert r.verify() == []
        assert [r.frame_bytes(5, k) for k in range(40)] == frames


def test_blob_chunk_size_is_checked(tmp_path):
    with pytest.raises(ValueError, match="blob_chunk_bytes"):
        _writer(tmp_path / "s.h5", _cameras(1), blob_chunk_bytes=0)
    assert not (tmp_path / "s.h5").exists()


def _corrupt_offset(f: h5py.File) -> None:
    f["cameras/101/left_offset"][3] = f["cameras/101/left_bytes"].shape[0] + 10


def _corrupt_time(f: h5py.File) -> None:
    f["cameras/102/capture_unix_ns"][6] = f["cameras/102/capture_unix_ns"][4]


def _corrupt_member(f: h5py.File) -> None:
    f["sets/members"][5, 2] = 999


def _corrupt_spread(f: h5py.File) -> None:
    f["sets/spread_ns"][2] += 1_000


def _corrupt_jpeg(f: h5py.File) -> None:
    off, n = f["cameras/102/right_offset"][4], f["cameras/102/right_length"][4]
    f["cameras/102/right_bytes"][off + n - 1] = 0


def _corrupt_length(f: h5py.File) -> None:
    f["cameras/101/seq"].resize((25,))


def _corrupt_gap(f: h5py.File) -> None:
    f["gaps/kind"][1] = 9


def _corrupt_summary(f: h5py.File) -> None:
    f["summary/frames"][0] = 31


@pytest.mark.parametrize(
    ("corrupt", "message"),
    [
        (_corrupt_offset, "camera 101: left bytes of rows 3 lie past the end"),
        (_corrupt_time, "camera 102: capture_unix_ns does not increase at rows 6"),
        (_corrupt_member, "sets 5 have members past the end"),
        (_corrupt_spread, "sets 2: spread_ns is not the max - min"),
        (_corrupt_jpeg, "camera 102: right images of rows 4 are not JPEG"),
        (_corrupt_length, "camera 101: frame table columns have 25 to 30 rows"),
        (_corrupt_gap, "gap records 1 have an unknown kind"),
        (_corrupt_summary, "camera 101: /summary counts 31 frames"),
    ],
)
def test_verify_reports_damage(session, corrupt, message):
    path, _ = session
    with h5py.File(path, "r+") as f:
        corrupt(f)
    with SessionReader(path) as r:
        problems = r.verify()
        assert any(p.startswith("error: ") and message in p for p in problems), problems
        r.sets(), r.gaps(), r.frame_table(101)  # the reader still serves the rest


def test_killed_writer_prefix_is_used_and_noted(tmp_path):
    """Tables one flush apart, as a kill mid-flush leaves them: a prefix and notes, no crash."""
    path = tmp_path / "s.h5"
    w = _writer(path, _cameras(1, 2))
    for row in range(20):
        for serial in (1, 2):
            _append(w, serial, row, (_image(serial, row, 0), _image(serial, row, 1)))
        w.append_set(T0_NS + row * PERIOD_NS, [row, row], 1)
    w.flush()
    w.abort()
    with h5py.File(path, "r+") as f:  # a set and a column that ran ahead of the rest
        for name in ("set_unix_ns", "spread_ns"):
            f[f"sets/{name}"].resize((21,))
        f["sets/members"].resize((21, 2))
        f["sets/members"][20] = [20, 20]
        f["cameras/2/capture_unix_ns"].resize((21,))
    with SessionReader(path) as r:
        assert not r.info.closed_cleanly and r.info.stopped_unix_ns == 0
        assert r.frame_count(2) == 20 and len(r.sets().set_unix_ns) == 20
        assert r.frame_bytes(2, 19) == (_image(2, 19, 0), _image(2, 19, 1))
        problems = r.verify()
        assert problems and all(p.startswith("note: ") for p in problems), problems
        assert any("sets 20 have members past the end" in p for p in problems)
        assert r.summary() == {}


def test_refuses_to_overwrite(session):
    path, _ = session
    before = path.read_bytes()
    with pytest.raises(SessionWriteError, match="already exists") as err:
        _writer(path, _cameras(1))
    assert isinstance(err.value, OSError) and isinstance(err.value, UserError)
    assert path.read_bytes() == before
    with pytest.raises(SessionWriteError, match="does not exist"):
        _writer(path.parent / "no" / "such" / "dir.h5", _cameras(1))


def test_writer_rejects_bad_calls(tmp_path):
    with _writer(tmp_path / "s.h5", _cameras(1, 2)) as w:
        with pytest.raises(ValueError, match="camera 3 is not in this session"):
            _append(w, 3, 0, (b"", b""))
        _append(w, 1, 0, (_image(1, 0, 0), _image(1, 0, 1)))
        with pytest.raises(ValueError, match="set member 0 of camera 2"):
            w.append_set(T0_NS, [0, 0], 0)
        with pytest.raises(ValueError, match="at least one member"):
            w.append_set(T0_NS, [-1, -1], 0)
        with pytest.raises(ValueError, match="needs 2 members"):
            w.append_set(T0_NS, [0], 0)
        with pytest.raises(ValueError):
            w.append_gap(
                1,
                kind=7,
                first_missing_frame_index=0,
                missing_count=0,
                start_unix_ns=0,
                end_unix_ns=0,
            )
    with pytest.raises(ValueError, match="closed"):
        w.flush()
    with pytest.raises(ValueError, match="encoding"):
        CameraInfo(
            camera_serial=1,
            node_id="n",
            resolution="HD1200",
            width=1,
            height=1,
            fps_nominal=30.0,
            encoding="png",
        )


def test_clear_errors_for_files_that_are_not_sessions(tmp_path, session):
    text = tmp_path / "notes.txt"
    text.write_text("not hdf5\n")
    with pytest.raises(SessionFormatError, match="not an HDF5 file"):
        SessionReader(text)
    with pytest.raises(SessionNotFoundError, match="no such session file") as err:
        SessionReader(tmp_path / "missing.h5")
    assert isinstance(err.value, FileNotFoundError) and isinstance(err.value, ValueError)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["data"] = np.arange(3)
        f.attrs["format"] = "something-else"
    with pytest.raises(SessionFormatError, match=r"not an EgoSurg session.*'something-else'"):
        SessionReader(other)
    path, _ = session
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 4  # 3 is a sealed session
    with pytest.raises(SessionFormatError, match=r"version 4 was written by a newer.*Upgrade"):
        SessionReader(path)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 2
        del f["gaps/kind"]
    with pytest.raises(SessionFormatError, match="missing or bad part"):
        SessionReader(path)


def test_h5dump_reads_the_layout(session):
    h5dump = shutil.which("h5dump")
    if h5dump is None:
        pytest.skip("h5dump is not installed (Debian package hdf5-tools)")
    path, expected = session
    out = subprocess.run([h5dump, "-H", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for name in ("left_bytes", "right_offset", "members", "first_missing_frame_index"):
        assert f'DATASET "{name}"' in out.stdout
    out = subprocess.run(
        [h5dump, "-a", "/format", str(path)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0 and '"egosurg-session"' in out.stdout
    with h5py.File(path, "r") as f:  # cut one image out with h5dump alone, as the docs show
        start, count = f["cameras/101/left_offset"][2], f["cameras/101/left_length"][2]
    jpeg = path.parent / "row2.jpg"
    cmd = [h5dump, "-d", "/cameras/101/left_bytes", "-s", str(start), "-c", str(count)]
    cut = subprocess.run(
        [*cmd, "-b", "LE", "-o", str(jpeg), str(path)], capture_output=True, timeout=60
    )
    assert cut.returncode == 0 and jpeg.read_bytes() == expected["frames"][101][2][0]


def test_a_live_file_is_readable_while_it_is_written(tmp_path):
    path = tmp_path / "live.h5"
    with _writer(path, _cameras(1)) as w:
        for row in range(5):
            _append(w, 1, row, (_image(1, row, 0), _image(1, row, 1)))
        w.flush()
        with SessionReader(path) as r:
            assert r.frame_count(1) == 5 and not r.info.closed_cleanly
            for row in range(5, 9):
                _append(w, 1, row, (_image(1, row, 0), _image(1, row, 1)))
            w.flush()
            r.refresh()
            assert r.frame_count(1) == 9
            assert r.frame_bytes(1, 8) == (_image(1, 8, 0), _image(1, 8, 1))


CHILD = """
import sys, time
sys.path.insert(0, {repo!r})
from tests.protocol.test_session import _append, _cameras, _image, _writer, T0_NS, PERIOD_NS
from protocol.session import GapKind
w = _writer({path!r}, _cameras(11, 12, 13))
row = 0
last = time.monotonic()
while True:
    for serial in (11, 12, 13):
        _append(w, serial, row, (_image(serial, row, 0), _image(serial, row, 1)))
    missing = row % 10 == 9
    w.append_set(T0_NS + row * PERIOD_NS, [row, row, -1 if missing else row], 1 if missing else 2)
    if row % 50 == 49:
        w.append_gap(12, kind=GapKind.SEQ_GAP, first_missing_frame_index=-1, missing_count=row,
                     start_unix_ns=0, end_unix_ns=1)
    row += 1
    if time.monotonic() - last >= 0.2:
        w.flush()
        print(row, row, flush=True)
        last = time.monotonic()
"""


def test_sigkill_leaves_every_flushed_frame_readable(tmp_path):
    path = tmp_path / "killed.h5"
    code = CHILD.format(repo=str(REPO), path=str(path))
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    lines: list[str] = []
    first = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            first.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert first.wait(30), "the writer never reported a flush"
        time.sleep(1.5)
    finally:
        proc.kill()  # SIGKILL: no handler, no atexit, no HDF5 close
        _, err = proc.communicate(timeout=30)
    reader.join(timeout=10)
    assert proc.returncode == -9, err
    complete = [line for line in lines if line.endswith("\n")]
    assert len(complete) >= 3, complete
    frames, sets = (int(x) for x in complete[-1].split())
    with SessionReader(path) as r:  # no h5clear
        assert not r.info.closed_cleanly
        for serial in (11, 12, 13):
            assert r.frame_count(serial) >= frames
            table = r.frame_table(serial)
            assert table["frame_index"][:frames].tolist() == list(range(frames))
            for row in range(frames):
                assert r.frame_bytes(serial, row) == (
                    _image(serial, row, 0),
                    _image(serial, row, 1),
                )
        set_table = r.sets()
        assert len(set_table.set_unix_ns) >= sets
        last = sets - 1
        assert set_table.members[last].tolist() == [last, last, -1 if last % 10 == 9 else last]
        assert len(r.gaps()) >= frames // 50
        problems = r.verify()
        assert all(p.startswith("note: ") for p in problems), problems
        in_file = r.frame_count(11)
    print(f"\nkilled writer: {frames} frames per camera reported flushed, {in_file} in the file")
    path.unlink()


def test_a_file_system_that_refuses_direct_io_gets_the_bytes_through_the_cache(
    tmp_path, monkeypatch
):
    """Some file systems open with O_DIRECT and then refuse the writes (EINVAL): the writer goes
    on through the page cache, losing nothing."""
    import errno

    from protocol.session import chunk_sink

    real = chunk_sink._pwrite
    refused: list[int] = []

    def pwrite(fd: int, data: Any, offset: int) -> int:
        if fd == w._sink._direct_fd:
            refused.append(offset)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, data, offset)

    monkeypatch.setattr(chunk_sink, "_pwrite", pwrite)
    path = tmp_path / "s.h5"
    frames = [(_image(3, row, 0), _image(3, row, 1)) for row in range(30)]
    w = _writer(path, _cameras(3))
    if not w._sink.direct_io:
        w.abort()
        pytest.skip(f"no direct I/O on {tmp_path} in the first place")
    with w:
        for row, data in enumerate(frames):
            _append(w, 3, row, data)
        w.flush()
        assert not w._sink.direct_io and len(refused) == 1
    with SessionReader(path) as r:
        assert r.verify() == []
        assert [r.frame_bytes(3, k) for k in range(30)] == frames


def test_a_dataset_that_cannot_grow_loses_that_frames_row_and_nothing_else(tmp_path, monkeypatch):
    """Growing a byte dataset fails (the file system refuses HDF5's allocation): that append
    raises SessionWriteError and its frame gets no row; later frames are stored right."""
    from protocol.session.datasets import Blob

    real = Blob._file_offset
    failures = iter([True])

    def fail_once(blob: Any) -> int:
        if next(failures, False):
            raise OSError(28, "No space left on device")
        return real(blob)

    frames = [(_image(1, row, 0), _image(1, row, 1)) for row in range(8)]
    with _writer(tmp_path / "s.h5", _cameras(1), blob_chunk_bytes=4096) as w:
        _append(w, 1, 0, frames[0])
        monkeypatch.setattr(Blob, "_file_offset", fail_once)
        with pytest.raises(SessionWriteError, match="check free disk space"):
            _append(w, 1, 1, frames[1])
        for row in range(1, 8):
            assert _append(w, 1, row, frames[row]) == row
    with SessionReader(tmp_path / "s.h5") as r:
        assert r.verify() == []
        assert [r.frame_bytes(1, row) for row in range(8)] == frames
