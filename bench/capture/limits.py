"""Part 2 of bench_capture.py: the raw limits of the same JPEG pairs through ZeroMQ (PUSH/PULL,
PUB/SUB), imagezmq's REQ/REP hub, ``SessionWriter`` and a plain file, each on its own."""

from __future__ import annotations

import multiprocessing as mp
import os
import struct
import time
from pathlib import Path

from bench.capture.measure import RESOLUTION, RIG_FPS, pair_header


def _zmq_end(ctx, kind: str, endpoint: str, *, sending: bool):
    """The sending or receiving end of a ``kind`` link ("push": PUSH/PULL, else PUB/SUB), timing
    out after 200 ms a send or 100 ms a receive. The PULL and the PUB end bind, the other
    connects, as the recorder's and the agents' sockets do."""
    import zmq

    push = kind == "push"
    if sending:
        sock = ctx.socket(zmq.PUSH if push else zmq.PUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDTIMEO, 200)
    else:
        sock = ctx.socket(zmq.PULL if push else zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVTIMEO, 100)
        if not push:
            sock.setsockopt(zmq.RCVHWM, 10_000)  # deep: this measures transport, not a policy
            sock.setsockopt(zmq.SUBSCRIBE, b"")
    if push != sending:
        sock.bind(endpoint)
    else:
        sock.connect(endpoint)
    return sock


def _zmq_sender(endpoint: str, kind: str, pairs: list, stop_at: float) -> None:
    """Sends [header, left, right] with copy=False until ``stop_at`` (time.monotonic)."""
    import zmq

    ctx = zmq.Context()
    sock = _zmq_end(ctx, kind, endpoint, sending=True)
    headers = [bytearray(pair_header("bench", 1, lft, rgt, ptp_locked=False)) for lft, rgt in pairs]
    seq = 0
    try:
        while time.monotonic() < stop_at:
            k = seq % len(pairs)
            h = headers[k]
            struct.pack_into("<Q", h, 8, seq)  # seq, so a subscriber can count drops
            try:
                sock.send_multipart([bytes(h), pairs[k][0], pairs[k][1]], copy=False)
            except zmq.Again:
                continue
            seq += 1
    finally:
        sock.close(linger=0)
        ctx.term()


def _zmq_receiver(endpoint: str, kind: str, start_at: float, end_at: float, q) -> None:
    import zmq

    ctx = zmq.Context()
    sock = _zmq_end(ctx, kind, endpoint, sending=False)
    count = nbytes = lost = 0
    last_seq = None
    t_first = t_last = None
    try:
        while (now := time.monotonic()) < end_at:
            try:
                parts = sock.recv_multipart(copy=False)
            except zmq.Again:
                continue
            seq = struct.unpack_from("<Q", parts[0].buffer, 8)[0]
            if now >= start_at:
                if t_first is None:
                    t_first = now
                    last_seq = seq - 1
                count += 1
                nbytes += sum(p.buffer.nbytes for p in parts)
                lost += max(0, seq - last_seq - 1)
                last_seq = seq
                t_last = now
    finally:
        sock.close(linger=0)
        ctx.term()
    span = (t_last - t_first) if t_first is not None and t_last > t_first else float("nan")
    q.put({"count": count, "bytes": nbytes, "lost": lost, "span": span})


def zmq_limit(kind: str, pairs: list, seconds: float) -> dict[str, float]:
    from sim.deploy import free_ports

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    endpoint = f"tcp://127.0.0.1:{free_ports(1)[0]}"
    t = time.monotonic()
    start_at, end_at = t + 3.0, t + 3.0 + seconds  # 3 s for both processes to import and join
    recv = ctx.Process(target=_zmq_receiver, args=(endpoint, kind, start_at, end_at, q))
    send = ctx.Process(target=_zmq_sender, args=(endpoint, kind, pairs, end_at + 0.5))
    recv.start()
    time.sleep(0.3)
    send.start()
    return _measured(q, [send, recv], seconds + 60, "msgs_s")


def _measured(q, procs: list, timeout_s: float, rate_key: str) -> dict:
    """What the measuring process put on ``q``, with its rate (``rate_key``: messages or images
    a second) and MB/s, once every process of the run has ended (terminated if it has not 10 s
    after)."""
    try:
        r = q.get(timeout=timeout_s)
    finally:
        for p in procs:
            p.join(timeout=10)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5)
    r[rate_key] = r["count"] / r["span"]
    r["mb_s"] = r["bytes"] / r["span"] / 1e6
    return r


def _izmq_hub(endpoint: str, start_at: float, end_at: float, q) -> None:
    import imagezmq
    import zmq

    hub = imagezmq.ImageHub(open_port=endpoint)
    hub.zmq_socket.setsockopt(zmq.RCVTIMEO, 100)
    hub.zmq_socket.setsockopt(zmq.LINGER, 0)
    count = nbytes = 0
    t_first = t_last = None
    try:
        while (now := time.monotonic()) < end_at:
            try:
                _msg, jpg = hub.recv_jpg()
            except zmq.Again:
                continue
            hub.send_reply(b"OK")
            if now >= start_at:
                t_first = now if t_first is None else t_first
                t_last = now
                count += 1
                nbytes += len(jpg)
    finally:
        hub.zmq_socket.close(linger=0)
        hub.zmq_context.term()
    span = (t_last - t_first) if t_first is not None and t_last > t_first else float("nan")
    q.put({"count": count, "bytes": nbytes, "span": span})


def _izmq_sender(endpoint: str, jpgs: list, stop_at: float, name: str) -> None:
    import imagezmq
    import zmq

    sender = imagezmq.ImageSender(connect_to=endpoint)
    sender.zmq_socket.setsockopt(zmq.RCVTIMEO, 1000)
    sender.zmq_socket.setsockopt(zmq.LINGER, 0)
    i = 0
    try:
        while time.monotonic() < stop_at:
            try:
                sender.send_jpg(name, jpgs[i % len(jpgs)])  # REQ send, then wait for b"OK"
            except zmq.Again:  # the hub has ended
                break
            i += 1
    finally:
        sender.zmq_socket.close(linger=0)
        sender.zmq_context.term()


def imagezmq_limit(jpgs: list, seconds: float, senders: int) -> dict[str, float]:
    from sim.deploy import free_ports

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    port = free_ports(1)[0]
    t = time.monotonic()
    start_at, end_at = t + 3.0, t + 3.0 + seconds
    hub = ctx.Process(target=_izmq_hub, args=(f"tcp://127.0.0.1:{port}", start_at, end_at, q))
    hub.start()
    time.sleep(0.3)
    procs = [
        ctx.Process(
            target=_izmq_sender,
            args=(f"tcp://127.0.0.1:{port}", jpgs, end_at + 0.5, f"sender-{k}"),
        )
        for k in range(senders)
    ]
    for p in procs:
        p.start()
    return _measured(q, [*procs, hub], seconds + 60, "images_s")


def hdf5_limit(
    pairs: list, seconds: float, directory: Path, cameras: int = 4, direct_io: bool | None = None
) -> dict[str, float]:
    """SessionWriter alone: append the pairs round-robin over ``cameras``, flush every 0.5 s.
    ``direct_io=False``: through the page cache (the writer's path before direct I/O)."""
    from protocol.session import CameraInfo, SessionWriter

    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "hdf5_limit.h5"
    path.unlink(missing_ok=True)
    os.sync()  # no writeback of earlier runs during this one
    infos = [
        CameraInfo(
            camera_serial=1000 + c,
            node_id="bench",
            resolution=RESOLUTION,
            width=1920,
            height=1200,
            fps_nominal=RIG_FPS,
            encoding="jpeg",
        )
        for c in range(cameras)
    ]
    w = SessionWriter(
        path,
        session_name="hdf5-limit",
        case_metadata={},
        cameras=infos,
        tolerance_ns=int(0.5e9 / RIG_FPS),
        software_version="bench",
        started_unix_ns=time.time_ns(),
        direct_io=direct_io,
    )
    frames = nbytes = 0
    cpu0 = os.times()
    t0 = time.perf_counter()
    last_flush = t0
    end = t0 + seconds
    k = 0
    try:
        while (now := time.perf_counter()) < end:
            left, right = pairs[k % len(pairs)]
            w.append_frame(
                1000 + k % cameras,
                left=left,
                right=right,
                capture_unix_ns=k,
                host_receive_unix_ns=k,
                recorder_receive_unix_ns=k,
                frame_index=k,
                seq=k,
                ptp_offset_ns=0,
                ptp_locked=False,
            )
            k += 1
            frames += 1
            nbytes += len(left) + len(right)
            if now - last_flush >= 0.5:
                w.flush()
                last_flush = now
        w.close(time.time_ns())
        span = time.perf_counter() - t0
        cpu1 = os.times()
    finally:
        path.unlink(missing_ok=True)
    cpu_s = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    return {
        "frames_s": frames / span,
        "mb_s": nbytes / span / 1e6,
        "frames": frames,
        "cpu_us_per_image": 1e6 * cpu_s / (2 * frames),
    }


def file_limit(
    pairs: list, seconds: float, directory: Path, cameras: int = 4, direct: bool = False
) -> dict[str, float]:
    """The page-cache floor under a buffered writer: the same images copied into one reused
    1 MiB buffer per camera side and written whole with ``os.pwrite`` to a plain file, in one
    thread; no HDF5, no tables, no flush. ``direct``: with ``O_DIRECT`` from page-aligned
    buffers, the disk's own rate for the writes ``SessionWriter`` makes."""
    import mmap

    import numpy as np

    from protocol.session import BLOB_CHUNK_BYTES as CHUNK

    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "file_limit.bin"
    path.unlink(missing_ok=True)
    os.sync()
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | (os.O_DIRECT if direct else 0)
    fd = os.open(path, flags, 0o644)
    buffers = [np.frombuffer(mmap.mmap(-1, CHUNK), np.uint8) for _ in range(2 * cameras)]
    fills = [0] * (2 * cameras)
    file_end = frames = nbytes = k = 0
    t0 = time.perf_counter()
    try:
        while time.perf_counter() - t0 < seconds:
            for side, image in enumerate(pairs[k % len(pairs)]):
                b = 2 * (k % cameras) + side
                src = np.frombuffer(image, np.uint8)
                pos = 0
                while pos < src.size:
                    take = min(src.size - pos, CHUNK - fills[b])
                    buffers[b][fills[b] : fills[b] + take] = src[pos : pos + take]
                    fills[b] += take
                    pos += take
                    if fills[b] == CHUNK:
                        os.pwrite(fd, buffers[b], file_end)
                        file_end += CHUNK
                        fills[b] = 0
                nbytes += src.size
            k += 1
            frames += 1
        span = time.perf_counter() - t0
    finally:
        os.close(fd)
        path.unlink(missing_ok=True)
    return {"frames_s": frames / span, "mb_s": nbytes / span / 1e6, "frames": frames}


def median_run(runs: list[dict[str, float]], key: str) -> dict:
    """The run with the median ``key``, with ``spread``: (lowest, highest) of ``key``."""
    runs = sorted(runs, key=lambda r: r[key])
    return dict(runs[len(runs) // 2], spread=(runs[0][key], runs[-1][key]))
