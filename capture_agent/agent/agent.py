"""``egosurg agent``: the capture daemon on one Jetson node.

Example::

    egosurg agent --config /etc/egosurg/node.toml
    sudo -u egosurg egosurg agent --check --config /etc/egosurg/node.toml   # install-day check

Per camera, a worker thread grabs frames (stamped by the source with the PTP-disciplined capture
time), encodes them (unless the source already did) and queues them. One publisher thread owns the
PUB socket: it gives each message the node's next ``seq`` and sends header + images without
copies, and once per ``status_interval_s`` it publishes an ``AgentStatus`` (fps, drops, queue
depth, PTP state). A control thread answers ``status`` and ``heartbeat`` on a REP socket.

A watchdog reopens a camera that stopped delivering (no frame for ``watchdog_timeout_s``) or
vanished, without touching the other cameras; a worker stuck inside a hung SDK call is abandoned
and replaced by a fresh one. If ``[ptp] require_lock`` is set, cameras are opened only once PTP is
locked: the ZED SDK slews rather than steps after a clock jump, so a camera opened before lock
would stamp wrong times for minutes.
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from dataclasses import dataclass, field

import zmq

from capture_agent.agent.preflight import check_node
from capture_agent.agent.ptp import PtpMonitor, PtpStatus
from capture_agent.control_server import ControlServer
from capture_agent.daemon import Progress, run_until_signal
from capture_agent.errors import CameraUnavailableError, Refused
from capture_agent.security import (
    CONTROL_MAX_BYTES,
    SUBSCRIPTION_MAX_BYTES,
    LinkGuard,
    LinkSecurity,
    harden,
)
from capture_agent.sources import make_source
from capture_agent.sources.base import CameraSource, GrabbedFrame
from protocol import __version__
from protocol.command import command_parser
from protocol.formats.camera_config import CameraConfig
from protocol.formats.node_config import NodeConfig
from protocol.images import EncodedPair, encode_pair
from protocol.os_thread import NamedThread
from protocol.wire import (
    AgentStatus,
    CameraStatus,
    ControlRequest,
    Encoding,
    FrameMessage,
    PtpState,
)

log = logging.getLogger(__name__)

GRAB_TIMEOUT_S = 0.25
STALL_LIMIT_S = 10.0  # a loop without progress for this long: exit, systemd restarts the agent


def latest_ptp(monitor: PtpMonitor) -> PtpStatus:
    st = monitor.latest
    if st is None:  # only before the monitor's first read
        return PtpStatus(state="unlocked", checked_unix_ns=time.time_ns(), detail="not read yet")
    return st


@dataclass
class _Counters:
    state: str = "closed"
    frames_captured: int = 0
    frames_dropped: int = 0  # frame-index gaps seen at the source plus queue overflows
    frames_published: int = 0
    reopen_count: int = 0
    last_capture_unix_ns: int | None = None
    last_frame_index: int | None = None
    error: str | None = None
    recent_capture_ns: collections.deque = field(
        default_factory=lambda: collections.deque(maxlen=64)
    )


@dataclass(frozen=True)
class _Outgoing:
    serial: int
    frame: GrabbedFrame
    pair: EncodedPair


class CameraWorker:
    """Grabs one camera in its own thread; the watchdog may replace the thread."""

    def __init__(self, entry: CameraConfig, node: NodeConfig, out: queue.Queue, ptp: PtpMonitor):
        self.entry = entry
        self.node = node
        self.out = out
        self.ptp = ptp
        self.lock = threading.Lock()
        self.counters = _Counters()
        self.source: CameraSource = make_source(entry)
        self.serial = self.source.serial
        self.last_progress = time.monotonic()
        self.grab_started: float | None = None  # set while inside source.grab()
        self._stop = threading.Event()
        self._generation = 0
        self._thread: threading.Thread | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        self._generation += 1
        gen = self._generation
        self._thread = NamedThread(
            target=self._run, args=(gen,), name=f"camera-{self.serial}-{gen}", daemon=True
        )
        self.last_progress = time.monotonic()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self.source.close()
        except Exception:  # closing a broken camera must not stop shutdown
            log.exception("closing camera %s", self.serial)

    def replace_hung_thread(self) -> None:
        """Abandon a thread stuck in the SDK and start a new one on a fresh source object."""
        log.warning(
            "camera %s: no progress for %.1f s; replacing its worker",
            self.serial,
            time.monotonic() - self.last_progress,
        )
        with self.lock:
            self.counters.state = "stalled"
            self.counters.reopen_count += 1
        self.source = make_source(self.entry)
        self.start()

    def factory_conf_text(self) -> str:
        try:
            return self.source.factory_conf_text()
        except Exception:  # informational only
            return ""

    # -- the loop -------------------------------------------------------------------------------
    def _set_state(self, state: str, error: str | None = None) -> None:
        with self.lock:
            self.counters.state = state
            self.counters.error = error

    def _run(self, generation: int) -> None:
        source = self.source  # this thread's own camera object; a replacement gets a new one
        last_frame_at = time.monotonic()
        while not self._stop.is_set() and generation == self._generation:
            self.last_progress = time.monotonic()
            try:
                if not source.is_open:
                    if not self._open(source):
                        self._stop.wait(self.node.reopen_interval_s)
                        continue
                    last_frame_at = time.monotonic()
                self.grab_started = time.monotonic()
                try:
                    frame = source.grab(GRAB_TIMEOUT_S)
                finally:
                    self.grab_started = None
                if generation != self._generation:
                    break  # the watchdog gave up on this thread while it was stuck
                now = time.monotonic()
                self.last_progress = now
                if frame is None:
                    if now - last_frame_at > self.node.watchdog_timeout_s:
                        log.warning(
                            "camera %s: no frame for %.1f s; reopening",
                            self.serial,
                            now - last_frame_at,
                        )
                        self._close_for_reopen(source, f"no frame for {now - last_frame_at:.1f} s")
                    continue
                last_frame_at = now
                self._deliver(frame)
            except CameraUnavailableError as exc:
                log.warning("camera %s vanished: %s; will reopen", self.serial, exc)
                self._close_for_reopen(source, f"camera vanished: {exc}")
            except Exception as exc:  # a camera thread must never die silently
                log.exception("camera %s: unexpected error; reopening", self.serial)
                self._close_for_reopen(source, f"error: {exc}")
                self._stop.wait(self.node.reopen_interval_s)
        if generation != self._generation:
            try:
                source.close()
            except Exception:  # the abandoned camera object is being thrown away anyway
                log.debug("closing an abandoned camera object failed", exc_info=True)

    def _open(self, source: CameraSource) -> bool:
        status = latest_ptp(self.ptp)
        if self.ptp.config.require_lock and status.state not in ("locked", "disabled"):
            self._set_state("closed", f"waiting for PTP lock before opening ({status.state})")
            return False
        try:
            source.open()
        except CameraUnavailableError as exc:
            self._set_state("reopening", f"cannot open: {exc}")
            return False
        # The state stays "closed" / "reopening" / "stalled" until the first frame arrives:
        # "streaming" means frames are flowing, not that the SDK call to open succeeded.
        with self.lock:
            if self.counters.state == "closed":
                self.counters.error = None  # e.g. no longer "waiting for PTP lock"
        log.info(
            "camera %s open (%s, %s at %g fps)",
            self.serial,
            self.entry.source,
            self.source.resolution.value,
            self.source.fps,
        )
        return True

    def _close_for_reopen(self, source: CameraSource, reason: str) -> None:
        try:
            source.close()
        except Exception:  # a broken camera must not stop the loop
            log.exception("camera %s: close failed", self.serial)
        with self.lock:
            self.counters.state = "reopening"
            self.counters.error = reason
            self.counters.reopen_count += 1

    def _deliver(self, frame: GrabbedFrame) -> None:
        enc = self.node.encoding
        if frame.encoded is not None and frame.encoded.encoding == enc:
            pair = frame.encoded
        else:
            assert frame.left_bgr is not None and frame.right_bgr is not None
            pair = encode_pair(frame.left_bgr, frame.right_bgr, enc, self.node.jpeg_quality)
        with self.lock:
            c = self.counters
            if c.last_frame_index is not None and frame.frame_index > c.last_frame_index + 1:
                c.frames_dropped += frame.frame_index - c.last_frame_index - 1
            c.last_frame_index = frame.frame_index
            c.frames_captured += 1
            c.last_capture_unix_ns = frame.capture_unix_ns
            c.recent_capture_ns.append(frame.capture_unix_ns)
            c.state = "streaming"
            c.error = None
        try:
            self.out.put_nowait(_Outgoing(self.serial, frame, pair))
        except queue.Full:
            with self.lock:
                self.counters.frames_dropped += 1
            log.warning(
                "camera %s: send queue full, frame %d dropped", self.serial, frame.frame_index
            )

    def status(self, queue_depth: int) -> CameraStatus:
        with self.lock:
            c = self.counters
            stamps = list(c.recent_capture_ns)
            fps = 0.0
            if len(stamps) >= 2 and stamps[-1] > stamps[0]:
                fps = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)
            stale = c.last_capture_unix_ns is None or (
                time.time_ns() - c.last_capture_unix_ns > 2e9
            )
            return CameraStatus(
                camera_serial=self.serial,
                state=c.state,
                fps_measured=0.0 if stale else round(fps, 2),
                frames_captured=c.frames_captured,
                frames_dropped=c.frames_dropped,
                frames_published=c.frames_published,
                queue_depth=queue_depth,
                reopen_count=c.reopen_count,
                last_capture_unix_ns=c.last_capture_unix_ns,
                error=c.error,
            )


class Agent:
    def __init__(self, config: NodeConfig) -> None:
        self.config = config
        self.ptp = PtpMonitor(config.ptp)
        self.out: queue.Queue[_Outgoing] = queue.Queue(maxsize=config.queue_frames)
        self.workers = [CameraWorker(e, config, self.out, self.ptp) for e in config.cameras]
        serials = [w.serial for w in self.workers]
        if len(set(serials)) != len(serials):
            from protocol.errors import ConfigError

            raise ConfigError(f"{config.source_path}: two [[cameras]] have the same serial")
        self.stopped = threading.Event()
        # Each loop's heartbeat (status, and systemd's watchdog) and the control socket's
        # request handling, shared with the recorder (capture_agent/control_server.py).
        self.progress = Progress("publish", "control", "watchdog")
        self.control = ControlServer(f"agent {config.node_id}", self._answer)
        self._ctx: zmq.Context = zmq.Context.instance()
        self._seq = 0
        self._status_seq = 0
        self._threads: list[threading.Thread] = []

    def ptp_state(self) -> PtpState:
        s = latest_ptp(self.ptp)
        return PtpState(state=s.state, master_offset_ns=s.master_offset_ns, gm_present=s.gm_present)

    def status(self) -> AgentStatus:
        depth = self.out.qsize()
        self._status_seq += 1
        return AgentStatus(
            node_id=self.config.node_id,
            sent_unix_ns=time.time_ns(),
            status_seq=self._status_seq,
            ptp=self.ptp_state(),
            cameras=tuple(w.status(depth) for w in self.workers),
            software_version=__version__,
        )

    def camera_info(self) -> list[dict]:
        """What the recorder stores per camera at the start of a session."""
        out = []
        for w in self.workers:
            res = w.source.resolution
            out.append(
                {
                    "camera_serial": w.serial,
                    "resolution": res.value,
                    "width": res.width,
                    "height": res.height,
                    "fps": w.source.fps,
                    "encoding": self.config.encoding,
                    "factory_conf": w.factory_conf_text(),
                }
            )
        return out

    # -- threads --------------------------------------------------------------------------------
    def start(self) -> None:
        # Its own context: one ZAP authenticator per context, with this agent's allow-list.
        # Keys are loaded first, so a missing or unprotected key stops the start cleanly.
        links = LinkSecurity.from_config(self.config.security)
        self._ctx = zmq.Context()
        self.guard = LinkGuard(self._ctx, links, f"agent {self.config.node_id}")
        pub = self._ctx.socket(zmq.PUB)
        harden(pub, SUBSCRIPTION_MAX_BYTES)
        pub.setsockopt(zmq.SNDHWM, max(100, 4 * self.config.queue_frames))
        self.guard.make_server(pub, f"{self.config.node_id}.frames")
        pub.bind(self.config.frames_bind)
        rep = self._ctx.socket(zmq.REP)
        harden(rep, CONTROL_MAX_BYTES)
        self.guard.make_server(rep, f"{self.config.node_id}.control")
        rep.bind(self.config.control_bind)
        self.ptp.start()
        for w in self.workers:
            w.start()
        self._threads = [
            NamedThread(target=self._publish, args=(pub,), name="publisher", daemon=True),
            NamedThread(target=self._control, args=(rep,), name="control", daemon=True),
            NamedThread(target=self._watchdog, name="watchdog", daemon=True),
        ]
        for t in self._threads:
            t.start()
        log.info(
            "agent %s: %d camera(s), frames on %s, control on %s",
            self.config.node_id,
            len(self.workers),
            self.config.frames_bind,
            self.config.control_bind,
        )

    def stop(self) -> None:
        self.stopped.set()
        for w in self.workers:
            w.stop()
        for t in self._threads:
            t.join(timeout=2.0)
        self.ptp.stop()
        guard = getattr(self, "guard", None)
        if guard is not None:
            guard.close()
            if not any(t.is_alive() for t in self._threads):
                self._ctx.term()  # every socket is closed: nothing can block it

    def _publish(self, pub: zmq.Socket) -> None:
        next_status = time.monotonic()
        by_serial = {w.serial: w for w in self.workers}
        try:
            while not self.stopped.is_set():
                self.progress.beat("publish")
                now = time.monotonic()
                if now >= next_status:
                    pub.send_multipart(self.status().to_parts())
                    next_status = now + self.config.status_interval_s
                try:
                    item = self.out.get(timeout=min(0.05, max(0.0, next_status - now)))
                except queue.Empty:
                    continue
                ptp = latest_ptp(self.ptp)
                f, pair = item.frame, item.pair
                msg = FrameMessage(
                    node_id=self.config.node_id,
                    camera_serial=item.serial,
                    frame_index=f.frame_index,
                    seq=self._seq,
                    capture_unix_ns=f.capture_unix_ns,
                    host_receive_unix_ns=f.host_receive_unix_ns,
                    ptp_offset_ns=ptp.master_offset_ns or 0,
                    ptp_locked=ptp.state == "locked",
                    encoding=Encoding(pair.encoding),
                    width=pair.width,
                    height=pair.height,
                    left=pair.left,
                    right=pair.right,
                )
                self._seq += 1
                pub.send_multipart(msg.to_parts(), copy=False)  # type: ignore[arg-type]
                w = by_serial[item.serial]
                with w.lock:
                    w.counters.frames_published += 1
        finally:
            pub.close(linger=0)

    def _control(self, rep: zmq.Socket) -> None:
        """Answer every request on the REP socket, whatever it holds (ControlServer); this
        thread ends only when the agent stops."""
        poller = zmq.Poller()
        poller.register(rep, zmq.POLLIN)
        try:
            while not self.stopped.is_set():
                self.progress.beat("control")
                try:
                    if poller.poll(100):
                        self.control.serve(rep)
                except zmq.ZMQError as exc:
                    if exc.errno in (zmq.ETERM, zmq.ENOTSOCK):
                        break  # the context or socket is closed: the agent is stopping
                    log.exception("control socket error; going on")
                    self.stopped.wait(0.1)
                except Exception:  # the control thread must never die: the recorder needs it
                    log.exception("control loop error; going on")
                    self.stopped.wait(0.1)
        finally:
            rep.close(linger=0)

    def _answer(self, req: ControlRequest) -> dict:
        """A request's result; ``Refused`` for the verbs an agent does not serve."""
        if req.verb == "heartbeat":
            return {"node_id": self.config.node_id}
        if req.verb == "status":
            return {
                "status": self.status().to_json(),
                "cameras_info": self.camera_info(),
                # how the agent's loops and control socket fare (fields the contract allows:
                # a receiver ignores what it does not know)
                "progress_age_s": self.progress.ages_s(),
                "control": self.control.counts(),
                # connection attempts this agent's links refused (unlisted key, plaintext)
                "links": {
                    "auth_refused": self.guard.refused if getattr(self, "guard", None) else {},
                    "insecure": self.config.security.insecure,
                },
            }
        raise Refused(
            f"an agent does not {req.verb} recordings; send '{req.verb}' to the recorder "
            "(egosurg record ...)"
        )

    def status_line(self) -> str:
        """One line for systemd's ``STATUS=`` (read from another thread: plain reads only)."""
        states = [w.counters.state for w in self.workers]
        streaming = states.count("streaming")
        others = sorted({st for st in states if st != "streaming"})
        return (
            f"{streaming} of {len(states)} cameras streaming"
            + (f" (others: {', '.join(others)})" if others else "")
            + f"; PTP {latest_ptp(self.ptp).state}"
        )

    def _watchdog(self) -> None:
        """Replace a worker stuck inside grab(): its SDK call hung. Opening may take long (the ZED
        SDK takes seconds), so only grab() is timed."""
        limit = self.config.watchdog_timeout_s + GRAB_TIMEOUT_S + 1.0
        while not self.stopped.wait(0.2):
            self.progress.beat("watchdog")
            for w in self.workers:
                started = w.grab_started
                if started is not None and time.monotonic() - started > limit:
                    w.replace_hung_thread()


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg agent", __doc__)
    parser.add_argument("--config", required=True, help="node.toml")
    parser.add_argument(
        "--check",
        action="store_true",
        help="check this node (SDK, cameras, PTP, clock, keys, ports ...), print a table and "
        "exit: 0 when it can record",
    )
    args = parser.parse_args(argv)
    config = NodeConfig.from_toml(args.config)
    if args.check:
        code, table = check_node(config)
        print(table)
        return code
    agent = Agent(config)
    return run_until_signal(
        agent.start,
        agent.stop,
        f"egosurg agent {config.node_id}: streaming {len(agent.workers)} camera(s) on "
        f"{config.frames_bind}; control on {config.control_bind}",
        progress=agent.progress.ages_s,
        stall_limit_s=STALL_LIMIT_S,
        status_line=agent.status_line,
        healthy=lambda: all(t.is_alive() for t in agent._threads),
    )
