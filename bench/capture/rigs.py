"""The rigs bench_capture.py records from: the simulated rig (``egosurg agent`` processes with
the sim source), and a replay rig whose two "agents" are feeders publishing real JPEG pairs."""

from __future__ import annotations

import dataclasses
import struct
import time
from pathlib import Path

from bench.capture.measure import JPEG_QUALITY, REPLAY_SERIAL0, RESOLUTION, pair_header

# Sessions sealed for a site key, as a deployed rig records them; [True] records plaintext
# sessions (bench_capture.py --plaintext-sessions: sealing's cost against the same rig)
PLAINTEXT_SESSIONS = [False]


def rig_spec(fps: float, duration_s: float, seed: int = 0, insecure: bool = False):
    from sim.deploy import SimRigSpec

    return SimRigSpec(
        insecure=insecure,
        plaintext=PLAINTEXT_SESSIONS[0],
        seed=seed,
        resolution=RESOLUTION,
        fps=fps,
        content_fps=1.0,  # one content frame per camera, rendered before streaming, repeated
        prerender_s=1.0,
        drop_probability=0.0,
        encoding="jpeg",
        jpeg_quality=JPEG_QUALITY,
        pre_encode=True,
        flush_interval_s=0.2,  # the rig.toml default
        # the start-time disk check reserves this much recording at the measured rate
        planned_duration_min=(duration_s + 5.0) / 60.0,
    )


def make_rig(
    directory: Path,
    cameras: int,
    fps: float,
    duration_s: float,
    seed: int = 0,
    insecure: bool = False,
):
    """``write_sim_rig`` for ``cameras`` stereo cameras: camera k >= 4 is camera ``k % 4`` of the
    sim world of seed ``seed + k // 4`` (``SimRigSpec.cameras``), two per node as on the rig."""
    from sim.deploy import write_sim_rig

    return write_sim_rig(
        directory, dataclasses.replace(rig_spec(fps, duration_s, seed, insecure), cameras=cameras)
    )


def make_replay_rig(
    directory: Path, cameras: int, fps: float, duration_s: float, insecure: bool = False
):
    """A rig.toml whose two "agents" are replay feeders; the same recorder settings and keys as
    the sim rig (written as ``write_sim_rig`` does, then pointed at the feeders' ports)."""
    from protocol.formats.rig_config import AgentEndpoint
    from protocol.toml_config import dumps
    from sim.deploy import SimRigFiles, free_ports, rig_config, write_keys, write_site_key

    if cameras < 2 or cameras % 2:
        raise SystemExit(f"replay cameras must be even and >= 2, got {cameras}")
    spec = rig_spec(fps, duration_s, insecure=insecure)
    ports = free_ports(5)
    nodes: dict[str, list[int]] = {"replay-a": [], "replay-b": []}
    for k in range(cameras):
        nodes["replay-a" if k % 2 == 0 else "replay-b"].append(REPLAY_SERIAL0 + k)
    if not insecure:
        write_keys(directory / "keys", ["recorder", "operator", *nodes])
    identity = None if spec.plaintext else write_site_key(directory)[1]  # rig_config names it
    endpoints = {}
    agents = []
    for k, (node, serials) in enumerate(nodes.items()):
        fr, ct = f"tcp://127.0.0.1:{ports[2 * k]}", f"tcp://127.0.0.1:{ports[2 * k + 1]}"
        endpoints[node] = (fr, ct)
        agents.append(
            AgentEndpoint(
                node_id=node,
                frames=fr,
                control=ct,
                cameras=tuple(serials),
                public_key="" if insecure else f"keys/{node}.key",
            )
        )
    control_bind = f"tcp://127.0.0.1:{ports[-1]}"
    rig = rig_config(spec, agents, control_bind, directory / "sessions", rig_name="bench-replay")
    directory.mkdir(parents=True, exist_ok=True)
    rig_path = directory / "rig.toml"
    comment = "bench_capture replay rig: the recorder settings of sim.deploy.write_sim_rig"
    rig_path.write_text(dumps(rig, comment=comment))
    files = SimRigFiles(
        directory=directory,
        node_configs={},
        rig_config=rig_path,
        session_dir=directory / "sessions",
        recorder_url=control_bind,
        epoch_unix_ns=0,
        serials_by_node={n: tuple(s) for n, s in nodes.items()},
        camera_index_by_serial={},
        spec=spec,
        identity=identity,
    )
    return files, endpoints


def feeder(
    node_id: str,
    frames_ep: str,
    control_ep: str,
    serials: list,
    fps: float,
    pairs: list,
    stop_at: float,
    stop_event,
    q,
    key_file: str | None = None,
) -> None:
    """Stands in for one capture agent: publishes valid frame messages of ``serials`` at ``fps``
    each, free-running with random phases, stamped with their scheduled time (as a camera is),
    with the node's ``seq`` and each camera's ``frame_index``; answers the recorder's ``status``
    control request with the cameras' info. Images are the real JPEG pairs, sent with copy=False.
    No rendering, no encoding, no per-frame validation: it costs the shared cores little. With
    ``key_file`` its sockets are CURVE servers of that key, as an agent's are (without a ZAP
    allow-list: the cost measured is the encryption, which is per message; ZAP is per
    connection)."""
    import zmq

    ctx = zmq.Context()
    pub, rep = _feeder_sockets(ctx, frames_ep, control_ep, key_file)
    control = _FeederControl(rep, node_id, _cameras_info(serials, fps))
    sent = 0
    max_lag_ns = 0
    try:
        sent, max_lag_ns = _publish(
            pub, control, _frame_templates(node_id, serials, pairs), serials, fps,
            stop_at=stop_at, stop_event=stop_event, rng_seed=hash(node_id) & 0xFFFF,
        )  # fmt: skip
    finally:
        pub.close(linger=0)
        rep.close(linger=0)
        ctx.term()
    q.put({"node": node_id, "sent": sent, "max_lag_ms": max_lag_ns / 1e6})


def _feeder_sockets(ctx, frames_ep: str, control_ep: str, key_file: str | None) -> tuple:
    """The feeder's PUB (frames) and REP (control) sockets, bound; CURVE servers with a key."""
    import zmq
    import zmq.auth

    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.setsockopt(zmq.SNDHWM, 480)  # the agent's: max(100, 4 * queue_frames)
    rep = ctx.socket(zmq.REP)
    rep.setsockopt(zmq.LINGER, 0)
    if key_file is not None:
        public, secret = zmq.auth.load_certificate(key_file)
        for sock in (pub, rep):
            sock.curve_publickey, sock.curve_secretkey = public, secret
            sock.curve_server = True
    pub.bind(frames_ep)
    rep.bind(control_ep)
    return pub, rep


def _frame_templates(node_id: str, serials: list, pairs: list) -> list:
    """Per camera: (its frame header to stamp, left JPEG, right JPEG)."""
    templates = []
    for c, serial in enumerate(serials):
        left, right = pairs[c % len(pairs)]
        h = pair_header(node_id, serial, left, right, ptp_locked=True)
        templates.append((bytearray(h), left, right))
    return templates


def _cameras_info(serials: list, fps: float) -> list[dict]:
    """The cameras' info an agent's ``status`` reply carries."""
    return [
        {
            "camera_serial": s,
            "resolution": RESOLUTION,
            "width": 1920,
            "height": 1200,
            "fps": fps,
            "encoding": "jpeg",
            "factory_conf": "",
        }
        for s in serials
    ]


class _FeederControl:
    """Answers the recorder's control requests; remembers when the first came (the start), from
    which on the feeder's lag is measured."""

    def __init__(self, rep, node_id: str, info: list[dict]) -> None:
        self._rep, self._node_id, self._info = rep, node_id, info
        self.measure_from: int | None = None  # unix ns

    def answer(self) -> None:
        from protocol.wire import ControlReply, ControlRequest

        while self._rep.poll(0):
            req = ControlRequest.from_bytes(self._rep.recv())
            result = (
                {"cameras_info": self._info} if req.verb == "status" else {"node_id": self._node_id}
            )
            reply = ControlReply(ok=True, result=result, request_id=req.request_id)
            self._rep.send(reply.to_bytes())
            if self.measure_from is None:
                self.measure_from = time.time_ns()


def _publish(
    pub,
    control: _FeederControl,
    templates: list,
    serials: list,
    fps: float,
    *,
    stop_at: float,
    stop_event,
    rng_seed: int,
) -> tuple[int, int]:
    """Publish every camera's frames on its schedule until ``stop_at`` (monotonic s) or the
    stop event; answer control requests between frames. Returns (frames sent, max lag ns)."""
    import heapq
    import random

    import zmq

    period = 1e9 / fps
    rng = random.Random(rng_seed)
    t0 = time.time_ns() + 200_000_000
    heap = [(t0 + rng.uniform(0, period), c, 0) for c in range(len(serials))]
    heapq.heapify(heap)
    seq = sent = 0
    max_lag_ns = 0
    pack = struct.Struct("<QQQqq")  # seq, serial, frame_index, capture, host_receive at 8..48
    while time.monotonic() < stop_at and not stop_event.is_set():
        due, c, idx = heap[0]
        now = time.time_ns()
        if due > now:
            control.answer()
            time.sleep(min((due - now) / 1e9, 0.005))
            continue
        heapq.heapreplace(heap, (due + period, c, idx + 1))
        h, left, right = templates[c]
        pack.pack_into(h, 8, seq, serials[c], idx, int(due), now)
        try:
            pub.send_multipart([bytes(h), left, right], copy=False)
        except zmq.Again:
            pass
        seq += 1
        sent += 1
        if control.measure_from is not None and due >= control.measure_from:
            max_lag_ns = max(max_lag_ns, now - int(due))
        if sent % 64 == 0:
            control.answer()
    return sent, max_lag_ns
