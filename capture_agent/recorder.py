"""``egosurg recorder``: subscribes to every agent of the rig, groups frames into synchronised sets
and writes one HDF5 session per recording.

Example::

    egosurg recorder --config /etc/egosurg/rig.toml

One I/O thread owns every socket and the session file, so control commands (start, stop) are
served in order between frames and two simultaneous starts cannot race. It:

- receives frame messages and agent status on one SUB socket per agent, a CURVE client of that
  agent's public key (``capture_agent/security.py``), so every message is known to come from
  that agent's key; malformed messages, unknown versions and messages that name another node
  or a camera that is not the agent's in rig.toml are counted, logged and skipped;
- while recording: stores every frame as received (no re-encoding), accounts for drops and gaps
  from frame indices, per-node sequence numbers and timestamps, feeds the synchroniser and stores
  each completed set; flushes the file every ``flush_interval_s`` (a crash loses at most that
  much) and stops cleanly before the disk's free space falls under ``disk_reserve_gb``;
- answers ``start``, ``stop``, ``status`` and ``heartbeat`` on its REP control socket, exactly
  one bounded reply per request whatever it holds (``capture_agent/control_server.py``).

Input cannot stop or exhaust it: the camera table holds only rig.toml's serials (at most
``MAX_UNLISTED_CAMERAS`` when it lists none), a listed camera is heard only from its own node,
frames stamped more than ``max_clock_skew_s`` from the recorder's clock are refused, and no
message is kept after it is handled; each refusal is counted in ``status``. The I/O loop beats a
progress heartbeat each iteration; ``status`` reports its age, and past ``STALL_LIMIT_S`` the
process exits for systemd to restart it (``capture_agent/daemon.py``, ``WatchdogSec=``).

Each agent's SUB socket queues what ``receive_buffer_mb`` allows (split over the agents, counted
at the largest legal frame message; at most ``RECEIVE_QUEUE_S`` of that agent's frames: see
``receive_hwm``). A recorder that falls further behind leaves the backlog in the agents' send
queues, then makes their PUB sockets drop messages, which the per-node ``seq`` shows as transport
losses: overload becomes counted loss, not unbounded memory.

At a stop, the take ends at the stop's time: the frames captured before it that are still queued
are received and written first (for up to ``STOP_WRITE_S``), until every streaming camera has
delivered a frame captured after it. Whatever of the take cannot be written then (the disk
reserve was reached, or the queue did not drain in time) is counted per camera as
``not_written_at_stop`` in the stop summary, never dropped silently.

The I/O thread never waits for the disk: the session file is written by the recording's writer
thread (``capture_agent/session_queue.py``), fed through a queue bounded in bytes
(``write_queue_mb``), and created at a start on a thread of its own (the start is refused when
that takes over ``OPEN_WAIT_S``). When the disk stalls, the queue fills; then frames are refused
and counted per camera (``not_written_disk_stalled``), ``status`` shows ``write_stalled_s`` and
the queued bytes, and once the disk answers the queue drains and the take goes on. A stop waits
for the queue up to ``STOP_WRITE_S`` and counts what it could not write (``not_written_at_stop``);
a file whose disk still does not answer is closed by the writer thread when it does.

When the session file cannot be written (disk full, I/O error), the take goes on: the writer
keeps what failed and retries it at each flush, frames arriving meanwhile are refused and counted
(``not_written_write_failed``), and ``status`` shows the error. After ``WRITE_FAILURE_STOP_S`` of
failures the take is stopped with the reason; the recorder itself keeps running. An exception
while handling one message or one periodic step is counted (``internal_errors`` in ``status``),
logged (rate-limited) and the loop goes on.

A start is refused, with the reason and what to do, when its arguments are unusable (a case
name that is not 1-64 of ``A-Z a-z 0-9 _ . -``; more than 64 metadata keys, keys over 64 or
values over 4096 characters, control or bidi characters; a planned duration that is not a number
> 0), when a camera the rig expects is not streaming, when an agent's PTP is not locked
(``require_ptp_lock``), or when the disk cannot hold
``planned_duration_min`` at the rig's measured data rate.
"""

from __future__ import annotations

import argparse
import collections
import logging
import math
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq

from capture_agent.accounting import StreamAccounting
from capture_agent.config import AgentEndpoint, RigConfig
from capture_agent.control_server import ControlServer, Refused
from capture_agent.daemon import Progress, run_until_signal
from capture_agent.recording import Recording
from capture_agent.security import (
    CONTROL_MAX_BYTES,
    LinkGuard,
    LinkSecurity,
    frame_message_max_bytes,
    frame_part_max_bytes,
    harden,
    load_public_key,
    make_client,
)
from capture_agent.session_queue import open_writer
from capture_agent.sync import SyncConfig, Synchroniser
from capture_agent.take_journal import TakeJournal, TakeResume
from capture_agent.take_journal import remove as remove_take_journal
from protocol import __version__
from protocol.agent_info import AgentReplyError, AgentStatusReply
from protocol.messages import (
    AgentStatus,
    ControlReply,
    ControlRequest,
    FrameMessage,
    MalformedMessageError,
    UnknownVersionError,
    decode_published,
)
from protocol.os_thread import NamedThread
from protocol.safe_text import brief, safe_text, unsafe_character
from protocol.session import CameraInfo, SessionWriteError, SessionWriter
from protocol.session_privacy import make_private_dir

log = logging.getLogger(__name__)

CASE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # with fullmatch: no trailing \n
MAX_META_KEYS = 64
MAX_META_KEY_CHARS = 64
MAX_META_VALUE_CHARS = 4096
MAX_UNLISTED_CAMERAS = 64  # the camera table's bound when rig.toml lists no cameras
STALL_LIMIT_S = 20.0  # the I/O loop without progress for this long: exit, systemd restarts
LIVE_WINDOW_S = 2.0
DISK_CHECK_S = 0.25
DISK_HEADROOM_S = 3.0  # seconds of recording kept free above the reserve
RECEIVE_QUEUE_S = 2.0  # the SUB socket's high-water mark, in seconds of one agent's frames
WRITE_FAILURE_STOP_S = 5.0  # a take whose file cannot be written for this long is stopped
STOP_WRITE_S = 3.0  # at a stop, write the queued frames of the take for at most this long
STOP_COUNT_S = 1.0  # then count (without writing) what is still queued, for at most this long
STOP_IDLE_S = 0.25  # a stop stops waiting for frames after this long without a message
OPEN_WAIT_S = 5.0  # a start whose session file is not created within this long is refused


class StartRefused(Refused):
    """A start that cannot go ahead; the message says why and what to do."""


@dataclass
class CameraLive:
    """What the recorder knows about a camera from its stream, recording or not."""

    serial: int
    node_id: str
    stamps: collections.deque = field(default_factory=lambda: collections.deque(maxlen=90))
    rx_monotonic: collections.deque = field(default_factory=lambda: collections.deque(maxlen=90))
    bytes_rx: collections.deque = field(default_factory=lambda: collections.deque(maxlen=90))
    last_rx_monotonic: float = 0.0
    ptp_offset_ns: int = 0
    ptp_locked: bool = False
    frames_rx: int = 0
    frames_refused_clock: int = 0  # stamped further than max_clock_skew_s from our clock

    def fps(self) -> float:
        s = list(self.stamps)
        if len(s) < 2 or time.monotonic() - self.last_rx_monotonic > LIVE_WINDOW_S:
            return 0.0
        return (len(s) - 1) / max((s[-1] - s[0]) / 1e9, 1e-9)

    def byte_rate(self) -> float:
        t = list(self.rx_monotonic)
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        return sum(list(self.bytes_rx)[1:]) / (t[-1] - t[0])

    def streaming(self) -> bool:
        return self.frames_rx > 0 and time.monotonic() - self.last_rx_monotonic < LIVE_WINDOW_S


class Recorder:
    _resume: TakeResume | None = None  # a take a killed recorder left unfinished (take_journal)

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.ctx: zmq.Context = zmq.Context()  # its own: one ZAP authenticator per context
        self.cameras: dict[int, CameraLive] = {}
        self.agent_status: dict[str, tuple[AgentStatus, float]] = {}
        self.recording: Recording | None = None
        self.malformed = 0
        self.unknown_version = 0
        self.frames_refused_sender = 0  # frames naming a node or camera not of their agent's key
        self.status_refused_sender = 0
        self.guard: LinkGuard | None = None
        self.subs: dict[zmq.Socket, AgentEndpoint] = {}
        self._server_keys: dict[str, bytes] = {}  # agent endpoint -> the agent's public key
        self.frames_refused_unknown_camera = 0  # serials not in rig.toml (or over the cap)
        self.progress = Progress("io")  # the I/O loop's heartbeat, for status and systemd
        self.internal_errors = 0  # bugs met while handling a message or a periodic step
        self.control = ControlServer(f"recorder {config.rig_name}", self._handle)
        self.stopped = threading.Event()
        self.last_stop_summary: dict[str, Any] | None = None
        self._thread: threading.Thread | None = None
        self._last_disk_check = 0.0
        self._disk_free = self._free_bytes()

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        self._resume_on_start()  # owner-only session folder; a take to resume (take_journal)
        self.open_sockets()
        self._thread = NamedThread(target=self._loop, name="recorder-io", daemon=True)
        self._thread.start()
        log.info(
            "recorder %s: %d agent(s), control on %s, sessions in %s",
            self.config.rig_name,
            len(self.config.agents),
            self.config.control_bind,
            self.config.output_dir,
        )

    def open_sockets(self) -> None:
        """One SUB socket per agent and the control REP (``start`` calls it; tests drive the
        I/O by hand). Every link is CURVE unless rig.toml says ``insecure = true``."""
        Path(self.config.output_dir).mkdir(parents=True, exist_ok=True)
        self.links: LinkSecurity = self.config.security.links()
        self.guard = LinkGuard(self.ctx, self.links, f"recorder {self.config.rig_name}")
        for a in self.config.agents:
            if not self.links.insecure:
                key = load_public_key(a.public_key, f"public key file of agent {a.node_id}")
                self._server_keys[a.frames] = self._server_keys[a.control] = key
            sub = self.ctx.socket(zmq.SUB)
            harden(sub, frame_part_max_bytes(self.config.max_image_bytes))
            sub.setsockopt(zmq.RCVHWM, receive_hwm(self.config, a))
            sub.setsockopt(zmq.SUBSCRIBE, b"")
            make_client(sub, self.links, self._server_keys.get(a.frames))
            sub.connect(a.frames)
            self.subs[sub] = a
        self.rep = self.ctx.socket(zmq.REP)
        harden(self.rep, CONTROL_MAX_BYTES)
        self.guard.make_server(self.rep, "recorder.control")
        self.rep.bind(self.config.control_bind)

    def close_sockets(self) -> None:
        for sub in self.subs:
            sub.close(linger=0)
        self.rep.close(linger=0)
        if self.guard is not None:
            self.guard.close()

    def receive_published(self, timeout_ms: int, max_messages: int = 256) -> int:
        """Wait up to ``timeout_ms`` for messages from any agent, then handle up to
        ``max_messages`` of each agent's; returns how many were handled."""
        poller = zmq.Poller()
        for sub in self.subs:
            poller.register(sub, zmq.POLLIN)
        ready = [s for s, _ in poller.poll(timeout_ms)]
        return self._receive(ready, max_messages)

    def _receive(self, ready: list, max_messages: int = 256) -> int:
        """Drain the ready SUB sockets, at most ``max_messages`` each, so that control and
        flushing come back regularly."""
        n = 0
        for sub in ready:
            agent = self.subs[sub]
            for _ in range(max_messages):
                try:
                    parts = sub.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                n += 1
                try:
                    self._on_published(parts, agent)
                except Exception:  # one message's bug must not end the take or the loop
                    self._internal_error("handling a message from agent " + agent.node_id)
        return n

    def _internal_error(self, what: str) -> None:
        """Count and log (rate-limited, with the traceback) an unexpected exception."""
        self.internal_errors += 1
        n = self.internal_errors
        if n <= 5 or n % 1000 == 0:
            log.exception("internal error #%d %s; the recorder goes on", n, what)

    def stop(self) -> None:
        self.stopped.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    # -- the I/O loop ---------------------------------------------------------------------------
    def _loop(self) -> None:
        poller = zmq.Poller()
        for sub in self.subs:
            poller.register(sub, zmq.POLLIN)
        poller.register(self.rep, zmq.POLLIN)
        try:
            while not self.stopped.is_set():
                events = dict(poller.poll(20))
                self._receive([s for s in self.subs if s in events])
                self.progress.beat("io")
                if self.rep in events:
                    self.control.serve(self.rep)  # one reply per request, whatever it holds
                try:
                    self._periodic()
                except Exception:
                    self._internal_error("in the periodic step")
        finally:
            if self.recording is not None:
                self._stop_recording("the recorder was shut down")
            self.close_sockets()

    def _on_published(self, parts: list, agent: AgentEndpoint) -> None:
        """A message from ``agent``'s SUB socket (so, over CURVE, from that agent's key)."""
        rx_ns = time.time_ns()
        try:
            msg = decode_published(parts)
        except UnknownVersionError as exc:
            self.unknown_version += 1
            if self.unknown_version <= 5 or self.unknown_version % 1000 == 0:
                log.warning("rejected message #%d: %s", self.unknown_version, exc)
            return
        except MalformedMessageError as exc:
            self.malformed += 1
            if self.malformed <= 5 or self.malformed % 1000 == 0:
                log.warning("rejected malformed message #%d: %s", self.malformed, exc)
            return
        if self._wrong_sender(msg, agent):
            return
        if isinstance(msg, AgentStatus):
            self.agent_status[msg.node_id] = (msg, time.monotonic())
            return
        self._on_frame(msg, rx_ns)

    def _wrong_sender(self, msg: FrameMessage | AgentStatus, agent: AgentEndpoint) -> bool:
        """True (counted, logged) for a message that names another node than the agent whose
        key sent it, or a camera that rig.toml does not list under that agent: a rogue or
        misconfigured key cannot speak for another node's cameras."""
        if isinstance(msg, AgentStatus):
            if msg.node_id == agent.node_id:
                return False
            self.status_refused_sender += 1
            n, what = self.status_refused_sender, "status"
        else:
            if msg.node_id == agent.node_id and (
                not agent.cameras or msg.camera_serial in agent.cameras
            ):
                return False
            self.frames_refused_sender += 1
            n, what = self.frames_refused_sender, f"frame of camera {msg.camera_serial}"
        if n <= 5 or n % 1000 == 0:
            log.warning(
                "refused %s #%d naming node %r from the link of agent %s (cameras %s)",
                what,
                n,
                msg.node_id,
                agent.node_id,
                list(agent.cameras),
            )
        return True

    def link_counts(self) -> dict[str, Any]:
        """What the links refused, for ``status``."""
        return {
            "auth_refused": self.guard.refused if self.guard is not None else {},
            "frames_refused_sender": self.frames_refused_sender,
            "status_refused_sender": self.status_refused_sender,
            "insecure": self.config.security.insecure,
        }

    def _on_frame(self, msg: FrameMessage, rx_ns: int) -> None:
        cam = self._camera_for(msg)
        if cam is None:
            return
        skew_ns = msg.capture_unix_ns - rx_ns
        if abs(skew_ns) > self.config.max_clock_skew_s * 1e9:
            # A clock step or a broken or hostile sender: such a stamp would corrupt the
            # rates and the sets (hours of empty windows), so it is refused and counted.
            cam.frames_refused_clock += 1
            n = cam.frames_refused_clock
            if n <= 5 or n % 1000 == 0:
                log.warning(
                    "camera %d: refused frame #%d stamped %.1f s %s the recorder's clock "
                    "(max_clock_skew_s = %g); check PTP on %s",
                    msg.camera_serial,
                    n,
                    abs(skew_ns) / 1e9,
                    "ahead of" if skew_ns > 0 else "behind",
                    self.config.max_clock_skew_s,
                    cam.node_id,
                )
            return
        now = time.monotonic()
        cam.node_id = msg.node_id
        cam.stamps.append(msg.capture_unix_ns)
        cam.rx_monotonic.append(now)
        cam.bytes_rx.append(msg.left_bytes + msg.right_bytes)
        cam.last_rx_monotonic = now
        cam.ptp_offset_ns = msg.ptp_offset_ns
        cam.ptp_locked = msg.ptp_locked
        cam.frames_rx += 1
        # No message is kept: each pins its images (up to 128 MiB); the console's preview
        # subscribes to the agent itself (rig_client.last_frame).
        if self.recording is not None:
            self.recording.write_frame(msg, rx_ns)

    def _camera_for(self, msg: FrameMessage) -> CameraLive | None:
        """The camera's entry; a new one only for a serial that rig.toml lists (or, when it
        lists none, while the table is under MAX_UNLISTED_CAMERAS). Others are counted."""
        owner = next(
            (a.node_id for a in self.config.agents if msg.camera_serial in a.cameras), None
        )
        if owner is not None and owner != msg.node_id:
            # a listed camera speaks only through its own agent (whose link checked node_id)
            self.frames_refused_sender += 1
            n = self.frames_refused_sender
            if n <= 5 or n % 1000 == 0:
                log.warning(
                    "refused frame #%d of camera %d from node %s: rig.toml lists it under %s",
                    n,
                    msg.camera_serial,
                    safe_text(msg.node_id),
                    owner,
                )
            return None
        cam = self.cameras.get(msg.camera_serial)
        if cam is not None:
            return cam
        listed = self.config.expected_cameras
        if (listed and msg.camera_serial not in listed) or (
            not listed and len(self.cameras) >= MAX_UNLISTED_CAMERAS
        ):
            self.frames_refused_unknown_camera += 1
            n = self.frames_refused_unknown_camera
            if n <= 5 or n % 1000 == 0:
                log.warning(
                    "refused frame #%d of camera %d from %s: %s",
                    n,
                    msg.camera_serial,
                    msg.node_id,
                    "not a camera of rig.toml"
                    if listed
                    else f"rig.toml lists no cameras and {MAX_UNLISTED_CAMERAS} already stream",
                )
            return None
        cam = self.cameras[msg.camera_serial] = CameraLive(msg.camera_serial, msg.node_id)
        log.info("camera %d streaming from %s", msg.camera_serial, msg.node_id)
        return cam

    def _periodic(self) -> None:
        self._resume_take_if_due()  # a take a killed recorder left (take_journal); never waits
        now = time.monotonic()
        rec = self.recording
        if rec is not None:
            rec.poll(time.time_ns())
            if now - rec.last_flush >= self.config.flush_interval_s:
                rec.request_flush()  # queued behind the frames; never waits for the disk
            if (
                rec.write_failing_since is not None
                and rec.write_failing_s() >= WRITE_FAILURE_STOP_S
            ):
                self._stop_recording(
                    f"writing {rec.writer.path} failed for {rec.write_failing_s():.0f} s "
                    f"({rec.write_error}); stopped. The file holds what was written before; "
                    "check the disk, then start a new recording",
                    write_queued=False,
                )
                return
        if now - self._last_disk_check >= DISK_CHECK_S:
            self._last_disk_check = now
            self._disk_free = self._free_bytes()
            # Stop while there is still room for what arrives before the next checks and for
            # closing the file: the reserve stays untouched.
            headroom = 0.0
            if rec is not None:
                # The rate the streams bring (a rate from the first frames of a recording
                # alone would be wild), or the write rate if that is higher.
                elapsed = max(now - rec.started_monotonic, 1.0)
                streams = sum(self.cameras[s].byte_rate() for s in rec.serials if s in self.cameras)
                rate = max(streams, rec.bytes_written / elapsed)
                headroom = DISK_HEADROOM_S * rate + 8e6
            if rec is not None and self._disk_free < self._reserve_bytes() + headroom:
                log.error("disk space under the reserve: stopping the recording cleanly")
                self._stop_recording(
                    f"the disk holding {self.config.output_dir} came within a few seconds of the "
                    f"reserve of {self.config.disk_reserve_gb:g} GB; stopped before it filled",
                    write_queued=False,
                )

    # -- control --------------------------------------------------------------------------------
    def _handle(self, req: ControlRequest) -> dict[str, Any]:
        if req.verb == "heartbeat":
            return {"rig_name": self.config.rig_name, "unix_ns": time.time_ns()}
        if req.verb == "status":
            return self.status()
        if req.verb == "start":
            return self._start_recording(req.args)
        if req.verb == "stop":
            if self.recording is None:
                raise StartRefused("not recording; nothing to stop")
            return self._stop_recording("stopped by request")
        raise Refused(f"the recorder does not know the verb {brief(req.verb)}")

    def _free_bytes(self) -> int:
        target = Path(self.config.output_dir)
        probe = target if target.exists() else target.parent
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        return shutil.disk_usage(probe).free

    def _reserve_bytes(self) -> float:
        return self.config.disk_reserve_gb * 1e9

    def _start_args(self, args: dict[str, Any]) -> tuple[str, dict[str, str], float]:
        """A start's case name, metadata and planned minutes, checked: they become a file
        name and a medical record's text, and are printed on operators' terminals."""
        case = args.get("case")
        if not isinstance(case, str) or not CASE_NAME.fullmatch(case):
            raise StartRefused(
                f"case name {brief(case)} is not usable as a file name; use 1 to 64 letters, "
                "digits, - _ . starting with a letter or digit"
            )
        meta = args.get("meta", {})
        if not isinstance(meta, dict):
            raise StartRefused("case metadata must be key=value text pairs")
        if len(meta) > MAX_META_KEYS:
            raise StartRefused(
                f"case metadata has {len(meta)} keys; at most {MAX_META_KEYS} are kept per case"
            )
        for key, value in meta.items():
            if not isinstance(value, str):
                raise StartRefused(
                    f"case metadata {brief(key)} is {type(value).__name__}; metadata must be "
                    "key=value text pairs"
                )
            if not 1 <= len(key) <= MAX_META_KEY_CHARS or len(value) > MAX_META_VALUE_CHARS:
                raise StartRefused(
                    f"case metadata {brief(key)} ({len(key)}-character key, {len(value)}-"
                    f"character value) is too long: keys 1 to {MAX_META_KEY_CHARS} characters, "
                    f"values at most {MAX_META_VALUE_CHARS}"
                )
            bad = unsafe_character(key) or unsafe_character(value)
            if bad is not None:
                raise StartRefused(
                    f"case metadata {brief(key)} holds the control character {bad}; metadata "
                    "is plain text on one line: no terminal escapes, bidi controls or line breaks"
                )
        planned = args.get("planned_duration_min", self.config.planned_duration_min)
        if (
            isinstance(planned, bool)
            or not isinstance(planned, int | float)
            or not math.isfinite(planned)
            or planned <= 0
        ):
            raise StartRefused(
                f"planned_duration_min = {brief(planned)}: give the planned length of the case "
                "in minutes, a number > 0 (the disk check needs it)"
            )
        return case, meta, float(planned)

    def _start_recording(self, args: dict[str, Any]) -> dict[str, Any]:
        case, meta, planned_min = self._start_args(args)  # first: a bad start says what is bad
        if self.recording is not None:
            raise StartRefused(
                f"already recording case '{self.recording.case}' to "
                f"{self.recording.writer.path}; stop it first (egosurg record stop)"
            )
        expected = self.config.expected_cameras or tuple(sorted(self.cameras))
        if not expected:
            raise StartRefused(
                "no camera is streaming yet; check that the agents run "
                "(systemctl status egosurg-agent) and that rig.toml points at them"
            )
        missing = [s for s in expected if s not in self.cameras or not self.cameras[s].streaming()]
        if missing:
            details = []
            for s in missing:
                cam = self.cameras.get(s)
                node = next(
                    (a.node_id for a in self.config.agents if s in a.cameras),
                    cam.node_id if cam else "?",
                )
                ago = (
                    "never seen"
                    if cam is None
                    else f"last frame {time.monotonic() - cam.last_rx_monotonic:.1f} s ago"
                )
                details.append(f"SN{s} on {node} ({ago})")
            raise StartRefused(
                "camera(s) not streaming: "
                + "; ".join(details)
                + ". Check the agent and its cameras (egosurg status), then start again"
            )
        if self.config.require_ptp_lock:
            for a in self.config.agents:
                st = self.agent_status.get(a.node_id)
                if st is None or time.monotonic() - st[1] > self.config.agent_timeout_s:
                    raise StartRefused(
                        f"no status from agent {a.node_id} for {self.config.agent_timeout_s:g} s;"
                        " is it running?"
                    )
                if st[0].ptp.state != "locked":
                    raise StartRefused(
                        f"PTP on {a.node_id} is '{st[0].ptp.state}', not locked: frames would "
                        "not share one clock. Check ptp4l/phc2sys on that node (pmc -u -b 0 "
                        "'GET TIME_STATUS_NP'), or set require_ptp_lock = false in rig.toml"
                    )
        rate = sum(self.cameras[s].byte_rate() for s in expected)
        need = self._reserve_bytes() + rate * planned_min * 60.0
        free = self._free_bytes()
        if free < need:
            raise StartRefused(
                f"not enough disk: {free / 1e9:.1f} GB free in {self.config.output_dir}, but a "
                f"{planned_min:g} min recording at {rate / 1e6:.1f} MB/s needs "
                f"{(need - self._reserve_bytes()) / 1e9:.1f} GB plus the "
                f"{self.config.disk_reserve_gb:g} GB reserve. Free space or plan a shorter case"
            )
        infos = self._camera_infos(expected)
        started_ns = time.time_ns()
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(started_ns / 1e9))
        path = Path(self.config.output_dir) / f"{case}_{stamp}.h5"
        n = 1
        while path.exists():
            n += 1
            path = path.with_name(f"{case}_{stamp}_{n}.h5")
        previous, part = self._resume.link(case) if self._resume else ("", 1)  # a resumed take

        def create() -> SessionWriter:
            return SessionWriter(
                path,
                previous_session_file=previous,
                take_part=part,
                session_name=case,
                case_metadata={str(k): v for k, v in meta.items()},
                cameras=infos,
                tolerance_ns=int(0.5e9 / self.config.fps),
                rig_config_text=self.config.toml_text,
                software_version=__version__,
                started_unix_ns=started_ns,
            )

        try:
            writer = open_writer(create, OPEN_WAIT_S)  # a stalled disk must not hold the loop
        except TimeoutError:
            raise StartRefused(
                f"the disk holding {self.config.output_dir} did not create the session file "
                f"within {OPEN_WAIT_S:g} s (writing stalls); check the disk, then start again"
            ) from None
        self.recording = Recording(
            writer=writer,
            sync=Synchroniser(
                SyncConfig(
                    camera_serials=tuple(expected),
                    fps=self.config.fps,
                    max_wait_ns=int(self.config.max_wait_ms * 1e6),
                )
            ),
            accounting=StreamAccounting(),
            case=case,
            started_unix_ns=started_ns,
            started_monotonic=time.monotonic(),
            serials=tuple(expected),
            last_flush=time.monotonic(),
            write_queue_bytes=int(self.config.write_queue_mb * 1e6),
        )
        log.info("recording case %s to %s (%d cameras)", case, path, len(expected))
        self._take_started(case, meta, planned_min, path, previous, part)
        return {
            "case": case,
            "file": str(path),
            "cameras": list(expected),
            "started_unix_ns": started_ns,
        }

    def _camera_infos(self, serials: tuple[int, ...]) -> list[CameraInfo]:
        """Ask each agent for its cameras' modes and factory files (stored in the session).

        The reply is checked field by field (``protocol/agent_info.py``): an agent that does
        not answer, answers ``ok: false`` or breaks the contract is refused with that reason.
        """
        infos: dict[int, CameraInfo] = {}
        for a in self.config.agents:
            needed = bool(a.cameras) or any(
                self.cameras.get(s) is not None and self.cameras[s].node_id == a.node_id
                for s in serials
            )
            reply = self._agent_status_reply(a.node_id, a.control, needed)
            if reply is None:
                continue
            for s in a.cameras:
                if reply.camera(s) is None:
                    raise StartRefused(
                        f"agent {a.node_id}'s status reply has no cameras_info entry for camera "
                        f"{s}, which rig.toml lists under it; check the serials in rig.toml "
                        f"(see {CONTRACT_DOC})"
                    )
            for ci in reply.cameras_info:
                owner = self._camera_owner(ci.camera_serial)
                if ci.camera_serial in serials and owner in (None, a.node_id):
                    infos[ci.camera_serial] = ci.to_session(a.node_id)
        missing = [s for s in serials if s not in infos]
        if missing:
            raise StartRefused(
                f"no agent reports camera(s) {missing}; check the serials in rig.toml"
            )
        return [infos[s] for s in serials]

    def _camera_owner(self, serial: int) -> str | None:
        """The node a camera belongs to: rig.toml's listing, else the node its frames name."""
        for a in self.config.agents:
            if serial in a.cameras:
                return a.node_id
        cam = self.cameras.get(serial)
        return cam.node_id if cam is not None else None

    def _agent_status_reply(
        self, node_id: str, endpoint: str, needed: bool
    ) -> AgentStatusReply | None:
        """An agent's checked ``status`` reply; None for an agent whose cameras the take does
        not need and that cannot give one (logged); a refusal naming the problem otherwise."""
        try:
            reply = self.request_agent(endpoint, "status")
            if reply is None:
                problem = (
                    f"agent {node_id} does not answer on {endpoint}; is it running "
                    "(systemctl status egosurg-agent on that node)?"
                    + (
                        ""
                        if self.config.security.insecure
                        else " If it runs, check that its public_key in rig.toml is current and "
                        "that its allowed_keys list the recorder's key"
                    )
                )
            elif not reply.ok:
                problem = f"agent {node_id} refused 'status': {(reply.error or '')[:300]}"
            else:
                return AgentStatusReply.from_json(reply.result, node_id=node_id)
        except AgentReplyError as exc:
            problem = f"agent {node_id}'s status reply {exc}; see {CONTRACT_DOC}"
        if needed:
            raise StartRefused(problem)
        log.warning("%s (none of its cameras is recorded)", problem)
        return None

    def request_agent(
        self, endpoint: str, verb: str, timeout_ms: int = 1500
    ) -> ControlReply | None:
        """One request to an agent: its reply (``ok`` or not), or None when none came in time.
        A reply that is not a valid EgoSurg reply to this request raises ``AgentReplyError``."""
        sock = self.ctx.socket(zmq.REQ)
        harden(sock, CONTROL_MAX_BYTES)
        sock.setsockopt(zmq.RCVTIMEO, timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, timeout_ms)
        request = ControlRequest(verb=verb)
        try:
            make_client(sock, self.links, self._server_keys.get(endpoint))
            sock.connect(endpoint)
            sock.send(request.to_bytes())
            raw = sock.recv()
        except zmq.Again:
            return None
        finally:
            sock.close(linger=0)
        return checked_reply(raw, request)

    def _drain_to_stop(self, rec: Recording, write: bool) -> None:
        """Receive the take's frames still queued (captured before the stop): written while
        ``write`` and for up to STOP_WRITE_S, then counted as not written for up to STOP_COUNT_S.
        Done when every camera still streaming has sent a frame captured after the stop."""
        rec.begin_stop(time.time_ns(), write=write)
        t0 = time.monotonic()
        waiting = {s for s in rec.serials if s in self.cameras and self.cameras[s].streaming()}
        while not waiting <= rec.passed_stop:
            elapsed = time.monotonic() - t0
            if elapsed > STOP_WRITE_S + STOP_COUNT_S:
                break
            rec.write_to_stop = write and elapsed < STOP_WRITE_S
            if time.monotonic() - rec.last_flush >= self.config.flush_interval_s:
                rec.request_flush()  # a crash while draining loses no more than at other times
            if not self.receive_published(int(STOP_IDLE_S * 1000)):
                break
        unwritten = sum(rec.not_written_at_stop.values())
        log.log(
            logging.WARNING if unwritten else logging.INFO,
            "stop: drained the queue in %.2f s; %d frames of the take not written%s",
            time.monotonic() - t0,
            unwritten,
            ""
            if waiting <= rec.passed_stop
            else f"; no frame after the stop from {sorted(waiting - rec.passed_stop)}",
        )

    def _stop_recording(self, reason: str, *, write_queued: bool = True) -> dict[str, Any]:
        rec = self.recording
        assert rec is not None
        self._drain_to_stop(rec, write_queued)
        summary = rec.finish(
            reason,
            {
                "malformed_messages": self.malformed,
                "unknown_version_messages": self.unknown_version,
            },
            write_s=STOP_WRITE_S,
            close_s=STOP_COUNT_S,
            # on the writer thread, once the file is closed (a stalled disk: later)
            on_closed=lambda: self._take_stopped(rec.writer.path.name),
        )
        self.recording = None
        self.last_stop_summary = summary
        log.info("stopped case %s: %s", rec.case, reason)
        return summary

    # -- a take resumed after a kill (capture_agent/take_journal.py) ----------------------------
    def _resume_on_start(self) -> None:
        make_private_dir(self.config.output_dir)  # sessions are medical records: 0700
        self._resume = TakeResume.load(self.config.output_dir)

    def _resume_take_if_due(self) -> None:
        """Start the journal's take again once every expected camera streams (I/O thread)."""
        resume = self._resume
        if resume is None or self.recording is not None or not resume.due():
            return
        expected = self.config.expected_cameras or tuple(sorted(self.cameras))
        streaming = [s in self.cameras and self.cameras[s].streaming() for s in expected]
        if not expected or not all(streaming):
            return
        try:
            self._start_recording(resume.start_args())
        except (Refused, SessionWriteError) as exc:
            resume.state = f"waiting: the start was refused: {exc}"
            log.warning("case %s not resumed yet (retrying): %s", resume.journal.case, exc)
        except Exception as exc:  # a bug must not take the I/O loop down
            resume.state = f"waiting: the start failed: {exc}"
            log.exception("case %s not resumed yet (retrying)", resume.journal.case)

    def _take_started(
        self, case: str, meta: dict, planned_min: float, path: Path, previous: str, part: int
    ) -> None:
        if self._resume is not None:
            self._resume.started(case, path.name)
        if previous:
            log.warning(
                "case %s resumed after the recorder was killed: part %d in %s continues %s",
                case,
                part,
                path,
                previous,
            )
        journal = TakeJournal(
            case=case,
            meta={str(k): str(v) for k, v in meta.items()},
            planned_duration_min=planned_min,
            file=path.name,
            take_part=part,
            written_unix_ns=time.time_ns(),
        )
        try:
            journal.write(self.config.output_dir)
        except OSError as exc:  # the take records; only a resume after a kill is lost
            log.error("cannot write the take journal in %s: %s", self.config.output_dir, exc)

    def _take_stopped(self, file_name: str) -> None:
        """Remove the take journal once the take's file is closed, unless a later take's
        journal replaced it meanwhile (a file closed late, after its disk stalled)."""
        try:
            journal = TakeJournal.read(self.config.output_dir)
            if journal is not None and journal.file != file_name:
                return
            remove_take_journal(self.config.output_dir)
        except OSError as exc:
            log.error("cannot remove the take journal in %s: %s", self.config.output_dir, exc)

    def status(self) -> dict[str, Any]:
        rec = self.recording
        cams = []
        serials = sorted(set(self.cameras) | set(self.config.expected_cameras))
        totals = rec.accounting.totals() if rec else {}
        for s in serials:
            cam = self.cameras.get(s)
            agent_drops = None
            if cam is not None and cam.node_id in self.agent_status:
                for cs in self.agent_status[cam.node_id][0].cameras:
                    if cs.camera_serial == s:
                        agent_drops = cs.frames_dropped
            cams.append(
                {
                    "serial": s,
                    "node_id": cam.node_id if cam else None,
                    "streaming": bool(cam and cam.streaming()),
                    "fps": round(cam.fps(), 2) if cam else 0.0,
                    "ptp_offset_ns": cam.ptp_offset_ns if cam else None,
                    "ptp_locked": cam.ptp_locked if cam else False,
                    "dropped_in_recording": totals[s].frames_dropped_camera if s in totals else 0,
                    "dropped_at_agent": agent_drops,
                    "frames_refused_clock": cam.frames_refused_clock if cam else 0,
                }
            )
        agents = []
        for a in self.config.agents:
            st = self.agent_status.get(a.node_id)
            agents.append(
                {
                    "node_id": a.node_id,
                    "frames": a.frames,
                    "control": a.control,
                    "public_key": self._server_keys.get(a.frames, b"").decode(),
                    "alive": bool(st and time.monotonic() - st[1] < self.config.agent_timeout_s),
                    "ptp_state": st[0].ptp.state if st else None,
                    "ptp_offset_ns": st[0].ptp.master_offset_ns if st else None,
                }
            )
        out: dict[str, Any] = {
            "rig_name": self.config.rig_name,
            "recording": rec is not None,
            "disk_free_bytes": self._disk_free,
            "output_dir": self.config.output_dir,
            "cameras": cams,
            "agents": agents,
            "malformed_messages": self.malformed,
            "unknown_version_messages": self.unknown_version,
            "links": self.link_counts(),
            # what the recorder refused and how its loop and control socket fare: counts, never
            # lists of what a sender made up, so the reply stays small whatever arrives
            "frames_refused_unknown_camera": self.frames_refused_unknown_camera,
            "frames_refused_clock": sum(c.frames_refused_clock for c in self.cameras.values()),
            "max_clock_skew_s": self.config.max_clock_skew_s,
            "control": self.control.counts(),
            "progress_age_s": self.progress.ages_s(),
            "internal_errors": self.internal_errors + (rec.queue.internal_errors if rec else 0),
            "stall_limit_s": STALL_LIMIT_S,
        }
        if rec is not None:
            out.update(
                {
                    "case": rec.case,
                    "file": str(rec.writer.path),
                    "duration_s": round(time.monotonic() - rec.started_monotonic, 2),
                    "sets": rec.sets_written,
                    "frames": rec.frames_written,
                    "bytes": rec.bytes_written,
                    "capture_to_durable_ms": rec.latency_ms(),
                    "write_failing_s": round(rec.write_failing_s(), 1),
                    "write_error": safe_text(rec.write_error, 500)
                    if rec.write_failing_since
                    else "",
                    "frames_not_written_write_failed": sum(rec.not_written_write_failed.values()),
                    # the writer thread inside one call for this long (a stalling disk), what
                    # waits for it, and what a full queue refused
                    "write_stalled_s": round(rec.write_stalled_s(), 1),
                    "write_queue_bytes": rec.queue.queued_bytes,
                    "write_queue_limit_bytes": rec.queue.max_bytes,
                    "frames_not_written_disk_stalled": sum(rec.not_written_disk_stalled.values()),
                }
            )
        if self.last_stop_summary is not None:
            out["last_recording"] = self.last_stop_summary
        if self._resume is not None:  # a take resumed (or to resume) after the recorder was killed
            out["take_resume"] = self._resume.status()
        return out

    def status_line(self) -> str:
        """One line for systemd's ``STATUS=`` (read from another thread: plain reads only)."""
        rec = self.recording
        cams = list(self.cameras.values())
        streaming = sum(1 for c in cams if c.streaming())
        expected = len(self.config.expected_cameras) or len(cams)
        if rec is not None:
            return (
                f"recording case {rec.case}: {rec.frames_written} frames written; "
                f"{streaming} of {expected} cameras streaming"
            )
        return f"idle; {streaming} of {expected} cameras streaming"


CONTRACT_DOC = "docs/capture.md#the-status-reply"


def checked_reply(raw: bytes, request: ControlRequest) -> ControlReply:
    """An agent's answer to ``request``; ``AgentReplyError`` names what is wrong with it."""
    try:
        reply = ControlReply.from_bytes(raw)
    except MalformedMessageError as exc:
        raise AgentReplyError("reply", f"is not a valid EgoSurg reply ({exc})") from None
    if reply.request_id != request.request_id:
        raise AgentReplyError(
            "request_id",
            f"answers request_id {reply.request_id[:40]!r}, not the request's "
            f"{request.request_id!r}; a reply must echo its request's request_id",
        )
    return reply


def receive_hwm(config: RigConfig, agent: AgentEndpoint) -> int:
    """``agent``'s SUB socket's high-water mark, in messages, from a byte budget.

    ZeroMQ bounds a queue in messages, so memory is bounded by counting every queued message at
    the largest legal frame message (``frame_message_max_bytes``: header and two images of
    ``max_image_bytes``, raw BGR at HD1200 unless rig.toml says less):

        hwm = min(receive_buffer_mb / agents / largest message,
                  RECEIVE_QUEUE_S * fps * the agent's cameras + 10 status messages)

    e.g. 1024 MB over 2 agents at 13.8 MB (raw HD1200) -> 37 messages (0.6 s of two cameras at
    30 fps); with ``max_image_bytes = 2000000`` (JPEG) 127 (2 s would take 130). The config
    refuses a budget under MIN_RECEIVE_MESSAGES per agent. A full queue leaves the backlog in
    the agent's send queue (the agent's memory), then the agent's PUB drops and ``seq`` counts
    the loss."""
    largest = frame_message_max_bytes(config.max_image_bytes)
    by_budget = int(config.receive_buffer_mb * 1e6 / max(len(config.agents), 1) // largest)
    cameras = len(agent.cameras) or 4  # an agent listed without cameras: a node's usual most
    by_time = math.ceil(RECEIVE_QUEUE_S * config.fps * cameras) + 10
    return max(1, min(by_budget, by_time))


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="egosurg recorder",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--config", required=True, help="rig.toml")
    args = parser.parse_args(argv)
    config = RigConfig.from_toml(args.config)
    recorder = Recorder(config)
    return run_until_signal(
        recorder.start,
        recorder.stop,
        f"egosurg recorder {config.rig_name}: {len(config.agents)} agent(s); control on "
        f"{config.control_bind}; sessions in {config.output_dir}",
        progress=recorder.progress.ages_s,
        stall_limit_s=STALL_LIMIT_S,
        status_line=recorder.status_line,
        healthy=lambda: recorder._thread is not None and recorder._thread.is_alive(),
    )
