"""The recorder's stop, receive queue and write queue, driven by hand: a real SUB socket fed by
a test PUB, a real session file, no agents. The recorder's thread is not started (but in the
last test), so the messages stay queued in ZeroMQ until the stop drains them, as they do in a
recorder that fell behind. The session file's writes run on the recording's writer thread."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zmq

from capture_agent.operator.control import format_status, format_summary
from capture_agent.recorder.accounting import StreamAccounting
from capture_agent.recorder.intake import CameraLive, CameraTable
from capture_agent.recorder.links import RECEIVE_QUEUE_S, receive_hwm
from capture_agent.recorder.recorder import Recorder
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.sync import SyncConfig, Synchroniser
from capture_agent.recorder.write_queue import WriteQueue
from protocol.formats.rig_config import RigConfig
from protocol.session import CameraInfo, SessionReader, SessionWriter, chunk_sink
from protocol.wire import ControlReply, ControlRequest, FrameMessage
from tests.helpers import frame_message, loopback_rig_config

FPS = 30.0
PERIOD_NS = int(1e9 / FPS)
SERIALS = (11, 12)
JPEG = b"\xff\xd8" + bytes(range(256)) * 4 + b"\xff\xd9"


def _config(tmp_path, frames: str, cameras: tuple[int, ...] = SERIALS) -> RigConfig:
    return loopback_rig_config(tmp_path / "sessions", frames=frames, cameras=cameras, fps=FPS)


def _frame(serial: int, index: int, seq: int, capture_unix_ns: int) -> list:
    return frame_message("n0", serial, index, seq, capture_unix_ns, JPEG).to_parts()


@pytest.fixture
def queued(tmp_path):
    """A recorder whose SUB socket holds 20 frames per camera captured before now and 3 after,
    with a recording open; yields (recorder, number of frames of the take per camera)."""
    ctx = zmq.Context.instance()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    recorder = Recorder(_config(tmp_path, f"tcp://127.0.0.1:{port}"))
    recorder.links.open()
    try:
        deadline = time.monotonic() + 10
        while not recorder.receive_published(50):  # PUB/SUB joins late: probe with camera 99
            assert time.monotonic() < deadline, "the SUB socket never connected"
            pub.send_multipart(_frame(99, 0, 0, time.time_ns()), copy=False)
        while recorder.receive_published(200):
            pass
        now = time.time_ns()
        infos = [
            CameraInfo(
                camera_serial=s,
                node_id="n0",
                resolution="TINY",
                width=8,
                height=4,
                fps_nominal=FPS,
                encoding="jpeg",
            )
            for s in SERIALS
        ]
        started = now - 2_000_000_000
        recorder.take.recording = Recording(
            writer=SessionWriter(
                tmp_path / "sessions" / "take.h5",
                session_name="take",
                case_metadata={},
                cameras=infos,
                tolerance_ns=PERIOD_NS // 2,
                software_version="test",
                started_unix_ns=started,
            ),
            sync=Synchroniser(SyncConfig(camera_serials=SERIALS, fps=FPS, max_wait_ns=500_000_000)),
            accounting=StreamAccounting(),
            case="take",
            started_unix_ns=started,
            started_monotonic=time.monotonic(),
            serials=SERIALS,
        )
        for s in SERIALS:  # both cameras stream (the start checked it)
            recorder.table.cameras[s] = CameraLive(
                s, "n0", frames_rx=1, last_rx_monotonic=time.monotonic()
            )
        seq = 1
        take = 20
        for k in range(take + 3):
            # frames k < take were captured before now, the rest 10 s after it
            capture = started + 1_000_000_000 + k * PERIOD_NS + (10**10 if k >= take else 0)
            for c, s in enumerate(SERIALS):
                pub.send_multipart(_frame(s, k, seq, capture + c * 1000), copy=False)
                seq += 1
        time.sleep(0.5)  # into the SUB socket's queue; nobody reads it yet
        yield recorder, take
    finally:
        if recorder.take.recording is not None:
            recorder.take.recording.writer.abort()
        recorder.links.close()
        pub.close(linger=0)


def test_a_stop_writes_the_frames_of_the_take_still_queued(queued):
    recorder, take = queued
    summary = recorder.stop_recording("stopped by request")
    assert summary["frames"] == take * len(SERIALS)
    assert summary["frames_not_written_at_stop"] == 0
    for s in SERIALS:
        cam = summary["cameras"][str(s)]
        assert cam["frames"] == take and cam["not_written_at_stop"] == 0
        assert cam["transport_lost"] == 0 and cam["dropped"] == 0
    with SessionReader(summary["file"]) as r:
        assert r.info.closed_cleanly and r.verify() == []
        for s in SERIALS:
            assert r.frame_table(s)["frame_index"].tolist() == list(range(take))
        assert len(r.sets().set_unix_ns) >= take - 1


def test_a_stop_that_cannot_write_counts_what_it_leaves(queued):
    """The disk reserve's stop writes nothing more, but every frame of the take is counted."""
    recorder, take = queued
    summary = recorder.stop_recording("disk", write_queued=False)
    assert summary["frames"] == 0
    assert summary["frames_not_written_at_stop"] == take * len(SERIALS)
    for s in SERIALS:
        assert summary["cameras"][str(s)]["not_written_at_stop"] == take
    with SessionReader(summary["file"]) as r:
        assert r.info.closed_cleanly and r.verify() == []
    # what 'egosurg record stop' prints: the operator sees the frames that are not in the file
    printed = format_summary(summary)
    assert f"{take * len(SERIALS)} frames were still queued" in printed
    for s in SERIALS:
        row = next(line for line in printed.splitlines() if line.startswith(f"SN{s}"))
        assert row.split()[-1] == str(take)


def _disk_full(monkeypatch) -> threading.Event:
    """Every write of image chunks fails with ENOSPC while the returned event is set."""
    real = chunk_sink._pwrite
    full = threading.Event()

    def pwrite(fd: int, data, offset: int) -> int:
        if full.is_set():
            raise OSError(28, "No space left on device")
        return real(fd, data, offset)

    monkeypatch.setattr(chunk_sink, "_pwrite", pwrite)
    return full


def _receive_all(recorder: Recorder) -> None:
    while recorder.receive_published(200):
        pass


def test_a_disk_full_for_a_moment_loses_only_the_frames_it_refused(queued, monkeypatch):
    """While the file cannot be written, the recording goes on, refusing and counting frames;
    when it can again, everything written before and after is in the file, and the stop says
    how many frames are not."""
    recorder, take = queued
    full = _disk_full(monkeypatch)
    rec = recorder.take.recording
    written = 10
    assert recorder.receive_published(1000, max_messages=written) == written
    full.set()
    rec.last_flush = 0.0
    recorder.periodic()  # a flush is due: it fails, the recording goes on
    assert rec.wait_written(10.0)  # the writer thread has done what was queued
    assert recorder.take.recording is rec and rec.write_failing_since is not None
    assert "No space" in rec.write_error
    _receive_all(recorder)  # the rest of the take arrives while the disk is full: refused
    assert rec.wait_written(10.0)
    status = recorder.status()  # what 'egosurg status' shows the operator meanwhile
    assert "No space" in status["write_error"]
    assert status["frames_not_written_write_failed"] == (take + 3) * len(SERIALS) - written
    assert "WRITING FAILS" in format_status(status)
    full.clear()
    rec.last_flush = 0.0  # due again: it succeeds, with the chunks that failed
    recorder.periodic()
    assert rec.wait_written(10.0)
    assert rec.write_failing_since is None
    summary = recorder.stop_recording("stopped by request")
    refused = summary["frames_not_written_write_failed"]
    assert summary["frames"] == written
    assert refused == (take + 3) * len(SERIALS) - written
    assert refused == sum(c["not_written_write_failed"] for c in summary["cameras"].values())
    with SessionReader(summary["file"]) as r:
        assert r.info.closed_cleanly and r.verify() == []
        for s in SERIALS:
            cam = summary["cameras"][str(s)]
            assert r.frame_count(s) == cam["frames"]
    assert f"{refused} frames are not in the file" in format_summary(summary)


def test_a_recording_that_cannot_write_for_long_stops_with_the_reason(queued, monkeypatch):
    """A disk that stays full stops the take (not the recorder), and the file keeps every frame
    of the last good flush."""
    from capture_agent.recorder import recorder as recorder_module

    recorder, take = queued
    full = _disk_full(monkeypatch)
    monkeypatch.setattr(recorder_module, "WRITE_FAILURE_STOP_S", 0.0)
    _receive_all(recorder)
    recorder.take.recording.flush()  # every frame of the take so far, durable
    flushed = recorder.take.recording.frames_written
    assert flushed == (take + 3) * len(SERIALS)
    full.set()
    recorder.take.recording.last_flush = 0.0
    recorder.periodic()  # queues the flush, which fails on the writer thread...
    assert recorder.take.recording.wait_written(10.0)
    recorder.periodic()  # ...and the next step sees the failure: the take stops
    assert recorder.take.recording is None
    summary = recorder.take.last_stop_summary
    assert "failed" in summary["reason"] and "No space left" in summary["reason"]
    assert "check the disk" in summary["reason"]
    with SessionReader(summary["file"]) as r:
        assert sum(r.frame_count(s) for s in SERIALS) == flushed
        assert all(line.startswith("note:") for line in r.verify())


def test_the_receive_queue_is_bounded_in_bytes_and_holds_seconds_where_it_can(tmp_path):
    """What queued frames may take in the recorder never exceeds receive_buffer_mb, counting
    each message at two raw HD1200 images; a budget that allows it holds RECEIVE_QUEUE_S."""
    import dataclasses

    raw_pair = 2 * 1920 * 1200 * 3  # the largest legal frame message's images
    cfg = _config(tmp_path, "tcp://127.0.0.1:1", cameras=(1, 2, 3, 4, 5, 6))
    hwm = receive_hwm(cfg, cfg.agents[0])
    assert hwm * raw_pair <= cfg.receive_buffer_mb * 1e6
    assert hwm >= 8
    roomy = dataclasses.replace(cfg, receive_buffer_mb=100_000.0)
    hwm = receive_hwm(roomy, roomy.agents[0])
    assert RECEIVE_QUEUE_S * FPS * 6 <= hwm < 2 * RECEIVE_QUEUE_S * FPS * 6
    jpeg = dataclasses.replace(cfg, max_image_bytes=500_000)  # a JPEG-only rig says so
    hwm = receive_hwm(jpeg, jpeg.agents[0])
    assert hwm >= RECEIVE_QUEUE_S * FPS * 6 and hwm * 1e6 <= jpeg.receive_buffer_mb * 1e6


# -- the writer thread: a stalling or failing disk never holds the I/O thread -----------------
# The session file's writes are stalled or failed at the chunk sink's one write call, as a
# frozen or full disk does (tests/e2e/test_faults.py freezes a real file system).
FRAME_BYTES = 2 * len(JPEG)


def _disk(monkeypatch) -> tuple[threading.Event, threading.Event]:
    """(stalled, full): while ``stalled`` is set every write of the session file waits (at most
    30 s), while ``full`` is set it fails with ENOSPC."""
    real = chunk_sink._pwrite
    stalled, full = threading.Event(), threading.Event()

    def pwrite(fd: int, data, offset: int) -> int:
        deadline = time.monotonic() + 30
        while stalled.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)
        if full.is_set():
            raise OSError(28, "No space left on device")
        return real(fd, data, offset)

    monkeypatch.setattr(chunk_sink, "_pwrite", pwrite)
    return stalled, full


def _wait_for(what: str, condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def _assert_sets_name_their_frames(path, tolerance_ns: int) -> None:
    """Every set member is a row of its camera whose capture time is the set's (within the
    tolerance): no set points at another frame than the one the synchroniser grouped."""
    with SessionReader(path) as r:
        assert r.verify() == []
        sets = r.sets()
        assert len(sets.set_unix_ns) > 0
        for col, s in enumerate(r.info.camera_serials):
            stamps = r.frame_table(s)["capture_unix_ns"]
            rows = sets.members[:, col]
            have = rows >= 0
            assert np.all(rows[have] < len(stamps))
            off = np.abs(stamps[rows[have]].astype(np.int64) - sets.set_unix_ns[have])
            assert np.all(off <= tolerance_ns), f"camera {s}: a set names another frame"


def test_a_stalling_disk_is_reported_and_costs_only_what_a_full_queue_refused(queued, monkeypatch):
    recorder, take = queued
    stalled, _ = _disk(monkeypatch)
    rec = recorder.take.recording
    rec.queue.max_bytes = 6 * FRAME_BYTES  # a queue of a few frames, so the stall fills it
    assert recorder.receive_published(1000, max_messages=4) == 4
    stalled.set()
    rec.request_flush()  # the flush's write blocks on the stalled disk...
    _wait_for("the stall to show", lambda: rec.write_stalled_s() > 0)
    while recorder.receive_published(200):  # ...and the I/O thread goes on receiving
        pass
    status = recorder.status()
    refused = status["frames_not_written_disk_stalled"]
    assert status["recording"] and status["write_stalled_s"] > 0
    assert 0 < refused < (take + 3) * len(SERIALS) - 4
    assert status["write_queue_bytes"] <= status["write_queue_limit_bytes"]
    assert "WRITING STALLED" in format_status(status)
    stalled.clear()  # the disk answers: the queue drains, the take goes on
    assert rec.wait_written(10.0)
    assert recorder.status()["write_stalled_s"] == 0
    summary = recorder.stop_recording("stopped by request")
    assert summary["frames_not_written_disk_stalled"] == refused
    for s in SERIALS:
        cam = summary["cameras"][str(s)]
        assert cam["frames"] + cam["not_written_disk_stalled"] == take + 3
    assert summary["frames"] == (take + 3) * len(SERIALS) - refused
    assert f"{refused} frames arrived while the write queue was full" in format_summary(summary)
    with SessionReader(summary["file"]) as r:
        assert r.info.closed_cleanly
        assert sum(r.frame_count(s) for s in SERIALS) == summary["frames"]
        assert r.summary()["extra"]["frames_not_written_disk_stalled"] == refused
    _assert_sets_name_their_frames(summary["file"], PERIOD_NS // 2)


def test_sets_skip_the_frames_the_writer_could_not_write(tmp_path, monkeypatch):
    """Frames refused while the disk was full leave their sets' members missing (-1), and the
    frames written after it are named by their own rows, not by their place in the stream."""
    _, full = _disk(monkeypatch)
    info = CameraInfo(
        camera_serial=7, node_id="n0", resolution="TINY", width=8, height=4,
        fps_nominal=FPS, encoding="jpeg",
    )  # fmt: skip
    t0 = time.time_ns()
    writer = SessionWriter(
        tmp_path / "take.h5", session_name="take", case_metadata={}, cameras=[info],
        tolerance_ns=PERIOD_NS // 2, software_version="test", started_unix_ns=t0,
    )  # fmt: skip
    q = WriteQueue(writer, max_bytes=1 << 20)

    def frame(k: int) -> FrameMessage:
        return FrameMessage.from_parts(_frame(7, k, k, t0 + k * PERIOD_NS))

    tickets = [q.put_frame(frame(k), t0) for k in range(4)]
    q.request_flush()
    assert q.wait_idle(10.0)
    full.set()
    q.request_flush()  # fails: the writer refuses frames until a flush gets through
    assert q.wait_idle(10.0) and q.write_failing_since is not None
    tickets += [q.put_frame(frame(k), t0) for k in (4, 5)]  # refused by the failing writer
    assert q.wait_idle(10.0)
    full.clear()
    q.request_flush()
    tickets += [q.put_frame(frame(k), t0) for k in range(6, 10)]
    for k, ticket in enumerate(tickets):
        q.put_set(t0 + k * PERIOD_NS, (ticket,), 0)
    q.close(lambda: {}, None)
    assert q.closed.wait(10.0)
    assert dict(q.not_written_write_failed) == {7: 2} and q.sets_not_written == 2
    with SessionReader(tmp_path / "take.h5") as r:
        indices = r.frame_table(7)["frame_index"].tolist()
        members = r.sets().members[:, 0].tolist()
    assert indices == [0, 1, 2, 3, 6, 7, 8, 9]
    assert [indices[m] for m in members] == [0, 1, 2, 3, 6, 7, 8, 9]


def _control(url: str, verb: str) -> ControlReply:
    sock = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.RCVTIMEO, 5000)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(url)
        sock.send(ControlRequest(verb=verb).to_bytes())
        return ControlReply.from_bytes(sock.recv())
    finally:
        sock.close()


def test_a_bug_in_frame_handling_is_counted_and_the_recorder_goes_on(tmp_path, monkeypatch):
    """A message whose handling raises (here: a bug planted for camera 12's frames) is counted
    in ``internal_errors`` and logged; the I/O thread keeps receiving and answering."""
    ctx = zmq.Context.instance()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    config = _config(tmp_path, f"tcp://127.0.0.1:{port}")
    recorder = Recorder(config)
    real = CameraTable.accept_frame

    def buggy(self, msg, rx_ns):
        if msg.camera_serial == 12:
            raise KeyError("a planted bug")
        return real(self, msg, rx_ns)

    monkeypatch.setattr(CameraTable, "accept_frame", buggy)
    recorder.start()
    try:
        k = 0

        def publish_some() -> bool:
            nonlocal k
            for s in SERIALS:
                pub.send_multipart(_frame(s, k, k, time.time_ns()), copy=False)
            k += 1
            return recorder.internal_errors >= 5 and 11 in recorder.table.cameras

        _wait_for("frames of both cameras to be handled", publish_some)
        assert recorder.alive()
        status = _control(config.control_bind, "status")
        assert status.ok and status.result["internal_errors"] >= 5
        cam = next(c for c in status.result["cameras"] if c["serial"] == 11)
        assert cam["streaming"]  # the good camera's frames are still handled
    finally:
        recorder.stop()
        pub.close()
    assert not recorder.alive()


def test_a_stop_while_the_disk_stalls_answers_and_the_file_closes_when_it_returns(
    queued, monkeypatch
):
    """The stop answers within its budget, counting the frames it could not write; the writer
    thread closes the file (cleanly, with the final counts) once the disk answers again."""
    from capture_agent.recorder import recorder as recorder_module

    recorder, take = queued
    stalled, _ = _disk(monkeypatch)
    monkeypatch.setattr(recorder_module, "STOP_WRITE_S", 0.5)
    monkeypatch.setattr(recorder_module, "STOP_COUNT_S", 0.5)
    rec = recorder.take.recording
    assert recorder.receive_published(1000, max_messages=4) == 4
    stalled.set()
    rec.request_flush()
    _wait_for("the stall to show", lambda: rec.write_stalled_s() > 0)
    t0 = time.monotonic()
    summary = recorder.stop_recording("stopped by request")
    assert time.monotonic() - t0 < 10.0
    assert "closing" in summary and recorder.take.recording is None
    assert summary["frames"] + summary["frames_not_written_at_stop"] <= take * len(SERIALS)
    assert summary["frames_not_written_at_stop"] > 0
    stalled.clear()
    assert rec.queue.closed.wait(10.0)
    with SessionReader(summary["file"]) as r:
        assert r.info.closed_cleanly and r.verify() == []
        final = r.summary()["extra"]
    assert final["frames"] + final["frames_not_written_at_stop"] == take * len(SERIALS)
