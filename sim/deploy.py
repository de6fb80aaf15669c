"""The simulated rig deployed as real processes: two capture agents and a recorder on loopback.

``write_sim_rig`` writes the ``node.toml`` of each simulated Jetson (two ZED X each, as on the
real rig) and a ``rig.toml`` for the recorder, with CURVE keys for every link (``keys/``: the
recorder, each node and an operator, whose key the rig's clients use). Its sessions are sealed
for a site key whose identity lives in ``reader-keys/`` (a reading workstation's folder): the
recorder's ``keys/`` holds only the public ``sim-site.recipient``; ``SimRigFiles.reader_env``
hands the identity to the ``egosurg`` reader commands as ``EGOSURG_IDENTITY``. It builds the
configs the agent and the recorder read (``protocol/formats/``: ``NodeConfig``,
``RigConfig``), so a bad value fails here, and writes them with the house's TOML writer.
``SimRig`` starts them as separate ``egosurg`` processes, waits until every camera streams, and
can kill and restart them for fault tests. The demo and the integration tests use it; it talks
to the processes only through the ``egosurg`` command and the control protocol, as an operator
would.

Example::

    files = write_sim_rig(Path("out/rig"), SimRigSpec(seed=0))
    with SimRig(files) as rig:
        rig.wait_streaming(timeout_s=120)
        rig.control("start", case="demo")
        time.sleep(10)
        summary = rig.control("stop")
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from protocol.camera import Resolution
from protocol.formats.camera_config import FaultSpec, SimSourceConfig
from protocol.formats.node_config import EncodingName, NodeConfig, PtpConfig
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.formats.sealing_config import RigSealingConfig
from protocol.formats.security_config import NodeSecurityConfig, RigSecurityConfig
from protocol.sealing import IDENTITY_ENV, generate_identity, write_identity
from protocol.toml_config import dumps
from sim.errors import SimRigError
from sim.timing import SIM_RIG_SOURCE
from sim.world import World

if TYPE_CHECKING:
    from sim.rig import ZedUnit

# the first lines of every file written here; key paths in them are relative to the file
_WRITTEN = "the simulated %s: written by sim.deploy (key paths are relative to this file)"
SITE_KEY = "sim-site"  # the key pair the sim rig's sessions are sealed for
READER_KEYS = "reader-keys"  # where its identity lives: not the recorder's keys/ folder


@dataclass(frozen=True, kw_only=True)
class SimRigSpec:
    """What ``write_sim_rig`` deploys. ``cameras`` is the number of stereo cameras: the sim world
    has 4 (two per node); camera ``k >= 4`` is camera ``k % 4`` of the world of seed
    ``seed + k // 4``, on the node of that camera index, so every camera has its own serial and
    clock (load tests of the recorder). Fewer than 4 uses the world's first cameras."""

    seed: int = 0
    cameras: int = 4
    phase: str = "intraoperative"
    resolution: str = "SVGA"
    fps: float = 15.0
    content_fps: float = 1.0
    prerender_s: float = 6.0
    drop_probability: float = 0.002
    jitter_ns_std: float = 150_000.0
    encoding: EncodingName = "jpeg"
    jpeg_quality: int = 85
    pre_encode: bool = True
    flush_interval_s: float = 0.2
    max_wait_ms: float = 500.0
    disk_reserve_gb: float = 0.5
    planned_duration_min: float = 1.0
    require_ptp_lock: bool = False
    # no PTP on loopback: the agents' clocks are the simulator's
    ptp: PtpConfig = field(default_factory=lambda: PtpConfig(source="none", require_lock=False))
    faults: dict[int, tuple[FaultSpec, ...]] = field(default_factory=dict)  # camera k -> faults
    insecure: bool = False  # plaintext links (insecure = true): only to measure CURVE's cost
    # unsealed sessions (plaintext = true): a bench's baseline, or tests of the capture path only
    plaintext: bool = False

    def __post_init__(self) -> None:
        if self.cameras < 1:
            raise ValueError(f"SimRigSpec.cameras must be >= 1, got {self.cameras}")


@dataclass(frozen=True)
class SimRigFiles:
    directory: Path
    node_configs: dict[str, Path]
    rig_config: Path
    session_dir: Path
    recorder_url: str
    epoch_unix_ns: int
    serials_by_node: dict[str, tuple[int, ...]]
    camera_index_by_serial: dict[int, int]
    spec: SimRigSpec
    identity: Path | None = None  # the site identity that opens the sessions (None: plaintext)

    def reader_env(self) -> dict[str, str]:
        """``os.environ`` with ``EGOSURG_IDENTITY`` naming the site identity: the environment
        of the ``egosurg`` commands that read this rig's sessions."""
        env = dict(os.environ)
        env.pop(IDENTITY_ENV, None)
        if self.identity is not None:
            env[IDENTITY_ENV] = str(self.identity)
        return env

    @property
    def keys_dir(self) -> Path:
        return self.directory / "keys"

    def sim_metadata(self) -> dict[str, str]:
        """The case metadata every recording of this rig carries (``SimRig.control("start")``):
        the world and the sim clock its pictures come from. The rig's sim time 0 is its epoch,
        and its prerendered content loops (``sim.timing.content_time_s``), so ``egosurg sim
        roles`` and ``sim contact`` need both to line the truth up with its pictures. A rig of
        more than 4 cameras mixes the worlds of several seeds: no single seed is written."""
        spec = self.spec
        meta = {
            "source": SIM_RIG_SOURCE,
            "phase": spec.phase,
            "sim_epoch_unix_ns": str(self.epoch_unix_ns),
            "sim_fps": repr(float(spec.fps)),
            "sim_content_fps": repr(float(spec.content_fps)),
            "sim_prerender_s": repr(float(spec.prerender_s)),
        }
        if spec.cameras <= 4:
            meta["seed"] = str(spec.seed)
        return meta

    def control_socket(self, ctx: Any) -> Any:
        """A REQ socket that may talk to the recorder: a CURVE client with the operator's key."""
        import zmq
        import zmq.auth

        sock = ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        if not self.spec.insecure:
            public, secret = zmq.auth.load_certificate(self.keys_dir / "operator.key_secret")
            sock.curve_publickey, sock.curve_secretkey = public, secret
            sock.curve_serverkey = zmq.auth.load_certificate(self.keys_dir / "recorder.key")[0]
        return sock


def write_keys(directory: Path, names: list[str]) -> None:
    """A CURVE keypair per name (pyzmq's certificate files, the secret one mode 0600, the folder
    0700), as ``egosurg keys generate`` makes them; existing keys are kept."""
    import zmq.auth

    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    directory.chmod(0o700)
    old = os.umask(0o077)
    try:
        for name in names:
            if not (directory / f"{name}.key_secret").exists():
                zmq.auth.create_certificates(directory, name)
    finally:
        os.umask(old)


def write_site_key(directory: Path) -> tuple[Path, Path]:
    """The rig's site key pair, as ``egosurg keys generate --kind site`` makes it: the identity
    in ``reader-keys/`` (a reading workstation's, never the recorder's), its public recipient
    copied to the recorder's ``keys/``; existing keys are kept. (recipient, identity) paths."""
    readers = directory / READER_KEYS
    identity = readers / f"{SITE_KEY}.identity"
    if not identity.exists():
        write_identity(generate_identity(SITE_KEY), readers)
    recipient = directory / "keys" / f"{SITE_KEY}.recipient"
    if not recipient.exists():
        recipient.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        recipient.write_text((readers / recipient.name).read_text())
    return recipient, identity


def free_ports(n: int) -> list[int]:
    socks, ports = [], []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
        ports.append(s.getsockname()[1])
    for s in socks:
        s.close()
    return ports


def _camera_units(spec: SimRigSpec) -> tuple[World, list[tuple[int, ZedUnit]]]:
    """The first world, and camera k of the rig as (its world's seed, its unit in that world)."""
    world = World.from_seed(spec.seed, phase=spec.phase)
    per_world = len(world.rig)
    worlds = {spec.seed: world}
    for k in range(per_world, spec.cameras):
        s = spec.seed + k // per_world
        if s not in worlds:
            worlds[s] = World.from_seed(s, phase=spec.phase)
    units = [
        (spec.seed + k // per_world, worlds[spec.seed + k // per_world].rig[k % per_world])
        for k in range(spec.cameras)
    ]
    serials = [u.serial for _, u in units]
    if len(set(serials)) != len(serials):
        raise SimRigError(f"two simulated cameras share a serial: {serials}; pick another seed")
    return world, units


def _camera(spec: SimRigSpec, k: int, seed: int, unit: ZedUnit, epoch: int) -> SimSourceConfig:
    """Camera ``k``'s ``[[cameras]]`` table."""
    encoded: dict[str, Any] = {}
    if spec.pre_encode and spec.encoding == "jpeg":
        encoded = {"pre_encode": "jpeg", "jpeg_quality": spec.jpeg_quality}
    return SimSourceConfig(
        seed=seed,
        phase=spec.phase,
        camera_index=unit.index,
        resolution=Resolution.parse(spec.resolution),
        fps=spec.fps,
        epoch_unix_ns=epoch,
        content_fps=spec.content_fps,
        prerender_s=spec.prerender_s,
        drop_probability=spec.drop_probability,
        jitter_ns_std=spec.jitter_ns_std,
        faults=spec.faults.get(k, ()),
        **encoded,
    )


def _node_config(
    spec: SimRigSpec, node: str, binds: tuple[str, str], cameras: list[SimSourceConfig]
) -> NodeConfig:
    """A node's node.toml; key paths relative to the file."""
    keys = NodeSecurityConfig(
        secret_key=f"keys/{node}.key_secret",
        allowed_keys=("keys/recorder.key", "keys/operator.key"),
    )
    return NodeConfig(
        node_id=node,
        frames_bind=binds[0],
        control_bind=binds[1],
        encoding=spec.encoding,
        jpeg_quality=spec.jpeg_quality,
        ptp=spec.ptp,
        security=NodeSecurityConfig(insecure=True) if spec.insecure else keys,
        cameras=tuple(cameras),
    )


def rig_config(
    spec: SimRigSpec,
    agents: list[AgentEndpoint],
    control_bind: str,
    sessions: Path,
    *,
    rig_name: str = "sim-or",
) -> RigConfig:
    """The recorder's rig.toml for ``agents``, with ``spec``'s recorder settings and the keys
    ``write_keys`` and ``write_site_key`` make (paths relative to the file); the capture bench's
    replay rig uses it."""
    keys = RigSecurityConfig(
        secret_key="keys/recorder.key_secret",
        operator_keys=("keys/operator.key",),
        operator_key="keys/operator.key_secret",
    )
    return RigConfig(
        rig_name=rig_name,
        fps=spec.fps,
        control_bind=control_bind,
        output_dir=str(sessions),
        require_ptp_lock=spec.require_ptp_lock,
        flush_interval_s=spec.flush_interval_s,
        max_wait_ms=spec.max_wait_ms,
        disk_reserve_gb=spec.disk_reserve_gb,
        planned_duration_min=spec.planned_duration_min,
        security=RigSecurityConfig(insecure=True) if spec.insecure else keys,
        sealing=RigSealingConfig(
            plaintext=spec.plaintext,
            recipients=() if spec.plaintext else (f"keys/{SITE_KEY}.recipient",),
        ),
        agents=tuple(agents),
    )


def write_sim_rig(directory: Path | str, spec: SimRigSpec | None = None) -> SimRigFiles:
    """Write node and rig configs for the simulated rig, on free loopback ports."""
    spec = spec or SimRigSpec()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    world, units = _camera_units(spec)
    # sim time 0 a moment ago: every agent shares this epoch, as PTP clocks share one timeline
    epoch = (time.time_ns() // 1_000_000_000) * 1_000_000_000
    nodes: dict[str, list[int]] = {}
    for k, (_, unit) in enumerate(units):
        nodes.setdefault(world.rig[unit.index].node_id, []).append(k)
    ports = free_ports(2 * len(nodes) + 1)
    if not spec.insecure:
        write_keys(out / "keys", ["recorder", "operator", *sorted(nodes)])
    identity = None if spec.plaintext else write_site_key(out)[1]
    node_paths: dict[str, Path] = {}
    serials_by_node: dict[str, tuple[int, ...]] = {}
    agents: list[AgentEndpoint] = []
    for n, (node, indices) in enumerate(sorted(nodes.items())):
        binds = (f"tcp://127.0.0.1:{ports[2 * n]}", f"tcp://127.0.0.1:{ports[2 * n + 1]}")
        cameras = [_camera(spec, k, *units[k], epoch) for k in indices]
        node_paths[node] = out / f"{node}.toml"
        cfg = _node_config(spec, node, binds, cameras)
        node_paths[node].write_text(dumps(cfg, comment=_WRITTEN % f"node {node}"))
        serials_by_node[node] = tuple(units[k][1].serial for k in indices)
        agents.append(
            AgentEndpoint(
                node_id=node,
                frames=binds[0],
                control=binds[1],
                cameras=serials_by_node[node],
                public_key="" if spec.insecure else f"keys/{node}.key",
            )
        )
    control_bind = f"tcp://127.0.0.1:{ports[-1]}"
    rig = rig_config(spec, agents, control_bind, out / "sessions")
    (out / "rig.toml").write_text(dumps(rig, comment=_WRITTEN % "rig's recorder"))
    return SimRigFiles(
        directory=out,
        node_configs=node_paths,
        rig_config=out / "rig.toml",
        session_dir=out / "sessions",
        recorder_url=control_bind,
        epoch_unix_ns=epoch,
        serials_by_node=serials_by_node,
        camera_index_by_serial={u.serial: u.index for _, u in units},
        spec=spec,
        identity=identity,
    )


def render_threads_per_agent(agents: int) -> int:
    """The renderer's threads (``NUMBA_NUM_THREADS``) for each of ``agents`` sim agents that
    share this machine: its cores shared out, at least one each.

    Each agent prerenders its cameras with Numba's parallel kernels, which by default start a
    thread per core in every process. Two agents on two cores then run four threads whose
    parallel loops wait at their barriers for a thread the other process holds off its core.
    Each pixel is computed on its own, so the frames are the same either way; what it saves is
    in BENCHMARKS.md ("A sim rig's prerendering", bench/bench_sim_rig.py)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, cores // max(agents, 1))


class SimRig:
    """The agent and recorder processes of a simulated rig. Logs go to ``<dir>/logs/``.

    ``render_threads``: the Numba threads of each agent process (``render_threads_per_agent``
    when None; 0 leaves Numba's default, a thread per core in every agent). A
    ``NUMBA_NUM_THREADS`` in the environment wins over both."""

    def __init__(self, files: SimRigFiles, *, render_threads: int | None = None) -> None:
        self.files = files
        self.logs = files.directory / "logs"
        self.logs.mkdir(exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}
        if render_threads is None:
            render_threads = render_threads_per_agent(len(files.node_configs))
        if render_threads < 0:
            raise ValueError(f"render_threads={render_threads} must be 0 (default) or more")
        self.render_threads = render_threads

    def _spawn(self, name: str, *args: str) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop(IDENTITY_ENV, None)  # the rig's processes hold no identity, as on a real rig
        if args[0] == "agent" and self.render_threads and "NUMBA_NUM_THREADS" not in env:
            env["NUMBA_NUM_THREADS"] = str(self.render_threads)
        with open(self.logs / f"{name}.log", "ab") as log:  # the child keeps its own handle
            proc = subprocess.Popen(
                [sys.executable, "-m", "protocol.cli", *args],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
            )
        self.procs[name] = proc
        return proc

    def start_agent(self, node: str) -> None:
        self._spawn(f"agent-{node}", "agent", "--config", str(self.files.node_configs[node]))

    def start_recorder(self) -> None:
        self._spawn("recorder", "recorder", "--config", str(self.files.rig_config))

    def start(self) -> SimRig:
        for node in self.files.node_configs:
            self.start_agent(node)
        self.start_recorder()
        return self

    def signal(self, name: str, sig: int = signal.SIGTERM) -> None:
        proc = self.procs[name]
        if proc.poll() is None:
            os.kill(proc.pid, sig)
        proc.wait(timeout=30)

    def control(self, verb: str, timeout_s: float = 10.0, **args: Any) -> dict[str, Any]:
        """One control request to the recorder; a refusal raises SimRigError with its reason."""
        import zmq

        from protocol.wire import ControlReply, ControlRequest

        ctx: zmq.Context = zmq.Context.instance()
        sock = self.files.control_socket(ctx)
        sock.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
        # a REQ socket's send waits for a connection; one whose handshake fails never comes
        sock.setsockopt(zmq.SNDTIMEO, int(timeout_s * 1000))
        if verb == "start":  # the recording says which world and sim clock it shows
            args = {**args, "meta": {**dict(args.get("meta") or {}), **self.files.sim_metadata()}}
        try:
            sock.connect(self.files.recorder_url)
            sock.send(ControlRequest(verb=verb, args=args).to_bytes())
            reply = ControlReply.from_bytes(sock.recv())
        except zmq.Again:
            raise SimRigError(
                f"the recorder did not answer '{verb}' in {timeout_s:g} s; see "
                f"{self.logs}/recorder.log"
            ) from None
        finally:
            sock.close(linger=0)
        if not reply.ok:
            raise SimRigError(reply.error or f"{verb} refused")
        return reply.result

    def wait_streaming(self, timeout_s: float = 180.0) -> dict[str, Any]:
        """Wait until the recorder sees every camera of the rig streaming."""
        deadline = time.monotonic() + timeout_s
        status: dict[str, Any] = {}
        while time.monotonic() < deadline:
            for name, proc in self.procs.items():
                if proc.poll() is not None:
                    raise SimRigError(
                        f"{name} exited with code {proc.returncode}; see {self.logs}/{name}.log"
                    )
            try:
                status = self.control("status", timeout_s=2.0)
            except SimRigError:
                time.sleep(0.5)
                continue
            expected = {s for ss in self.files.serials_by_node.values() for s in ss}
            streaming = {c["serial"] for c in status["cameras"] if c["streaming"]}
            if expected <= streaming:
                return status
            time.sleep(0.5)
        raise SimRigError(
            f"cameras not all streaming after {timeout_s:g} s: {status}; see logs in {self.logs}"
        )

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                try:
                    os.kill(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        for proc in self.procs.values():
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)

    def __enter__(self) -> SimRig:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
