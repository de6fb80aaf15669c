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
thread (``capture_agent/recorder/write_queue.py``), fed through a queue bounded in bytes
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

This module owns the ``Recorder`` core: its lifecycle, sockets, the I/O loop, the periodic step
(flushes, write failures, the disk check) and the control verbs. The rest lives beside it, in
functions that take the recorder: ``recorder_intake.py`` (each published message, the camera
table), ``recorder_start.py`` (a start's checks, the agents' camera infos, the new take),
``recorder_take.py`` (the stop and its drain, the take journal's resume) and
``recorder_status.py`` (the ``status`` reply).
"""

from __future__ import annotations

import argparse
import logging
import math
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import zmq

from capture_agent.config import AgentEndpoint, RigConfig
from capture_agent.control_server import ControlServer, Refused
from capture_agent.daemon import Progress, run_until_signal
from capture_agent.recorder import intake as recorder_intake
from capture_agent.recorder import start as recorder_start
from capture_agent.recorder import status as recorder_status
from capture_agent.recorder import take as recorder_take
from capture_agent.recorder.intake import LIVE_WINDOW_S, MAX_UNLISTED_CAMERAS, CameraLive
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.start import (
    CASE_NAME,
    CONTRACT_DOC,
    MAX_META_KEY_CHARS,
    MAX_META_KEYS,
    MAX_META_VALUE_CHARS,
    OPEN_WAIT_S,
    StartRefused,
    checked_reply,
)
from capture_agent.recorder.take import StopLimits
from capture_agent.recorder.take_journal import TakeResume
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
from protocol.os_thread import NamedThread
from protocol.safe_text import brief
from protocol.wire import AgentStatus, ControlReply, ControlRequest, FrameMessage

# Moved to the sibling modules and kept importable from here: ``capture_agent.recorder.recorder`` is
# where callers and tests have always found them.
__all__ = [
    "CASE_NAME",
    "CONTRACT_DOC",
    "LIVE_WINDOW_S",
    "MAX_META_KEYS",
    "MAX_META_KEY_CHARS",
    "MAX_META_VALUE_CHARS",
    "MAX_UNLISTED_CAMERAS",
    "OPEN_WAIT_S",
    "RECEIVE_QUEUE_S",
    "CameraLive",
    "Recorder",
    "StartRefused",
    "checked_reply",
    "main",
    "receive_hwm",
]

log = logging.getLogger(__name__)

STALL_LIMIT_S = 20.0  # the I/O loop without progress for this long: exit, systemd restarts
DISK_CHECK_S = 0.25
DISK_HEADROOM_S = 3.0  # seconds of recording kept free above the reserve
RECEIVE_QUEUE_S = 2.0  # the SUB socket's high-water mark, in seconds of one agent's frames
# read at each use (tests shorten them): the sibling modules get them as arguments
WRITE_FAILURE_STOP_S = 5.0  # a take whose file cannot be written for this long is stopped
STOP_WRITE_S = 3.0  # at a stop, write the queued frames of the take for at most this long
STOP_COUNT_S = 1.0  # then count (without writing) what is still queued, for at most this long
STOP_IDLE_S = 0.25  # a stop stops waiting for frames after this long without a message


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
        recorder_take.resume_on_start(
            self
        )  # owner-only session folder; a take to resume (take_journal)
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
                    recorder_intake.on_published(self, parts, agent)
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
        """A message from ``agent``'s SUB socket (``recorder_intake.on_published``)."""
        recorder_intake.on_published(self, parts, agent)

    def _on_frame(self, msg: FrameMessage, rx_ns: int) -> None:
        """A decoded frame from its own agent (``recorder_intake.on_frame``)."""
        recorder_intake.on_frame(self, msg, rx_ns)

    def link_counts(self) -> dict[str, Any]:
        """What the links refused, for ``status``."""
        return recorder_status.link_counts(self)

    def _periodic(self) -> None:
        recorder_take.resume_take_if_due(
            self
        )  # a take a killed recorder left (take_journal); never waits
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
        """A start's case name, metadata and planned minutes, checked (``recorder_start``)."""
        return recorder_start.start_args(args, self.config.planned_duration_min)

    def _start_recording(self, args: dict[str, Any]) -> dict[str, Any]:
        return recorder_start.start_recording(self, args)

    def request_agent(
        self, endpoint: str, verb: str, timeout_ms: int = 1500
    ) -> ControlReply | None:
        """One request to an agent: its reply (``ok`` or not), or None when none came in time.
        A reply that is not a valid EgoSurg reply to this request raises ``AgentReplyError``."""
        return recorder_start.request_agent(self, endpoint, verb, timeout_ms)

    def _stop_recording(self, reason: str, *, write_queued: bool = True) -> dict[str, Any]:
        limits = StopLimits(write_s=STOP_WRITE_S, count_s=STOP_COUNT_S, idle_s=STOP_IDLE_S)
        return recorder_take.stop_recording(self, reason, limits, write_queued=write_queued)

    # -- the report -----------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        return recorder_status.status(self, STALL_LIMIT_S)

    def status_line(self) -> str:
        """One line for systemd's ``STATUS=`` (read from another thread: plain reads only)."""
        return recorder_status.status_line(self)


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
    parser = command_parser("egosurg recorder", __doc__)
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
