"""``egosurg recorder``: subscribes to every agent of the rig, groups frames into synchronised sets
and writes one HDF5 session per recording.

Example::

    egosurg recorder --config /etc/egosurg/rig.toml

One I/O thread owns every socket and the session file, so control commands (start, stop) are
served in order between frames and two simultaneous starts cannot race. It:

- receives frame messages and agent status on one SUB socket per agent, a CURVE client of that
  agent's public key (``capture_agent/security.py``), so every message is known to come from
  that agent's key; malformed messages, unknown versions and messages that name another node
  or a camera that is not the agent's in rig.toml are counted, logged and skipped; a link that
  drops or whose handshake is refused is made again with backoff (``links.AgentLinks``), and
  each drop, refusal and return is counted per agent in ``status`` and recorded as a session
  event of the take in progress;
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
``links.receive_hwm``). A recorder that falls further behind leaves the backlog in the agents' send
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
``planned_duration_min`` at the cameras' configured rate (fps x their typical frame).

This module owns the ``Recorder``: it composes the parts the I/O thread changes, each with one
owner (``intake.CameraTable``: the cameras, the agents' status and what was refused;
``links.AgentLinks``: the sockets and keys; ``disk.DiskBudget``: free space and the reserve;
``take.TakeState``: the take in progress, the last stop and a take to resume), and owns the
loop: its lifecycle, the periodic step (flushes, write failures, the disk check, the resume) and
the control verbs. ``start`` checks and begins a take, ``status`` builds the reply.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zmq

from capture_agent.control_server import ControlServer
from capture_agent.daemon import Progress, run_until_signal
from capture_agent.errors import Refused
from capture_agent.link_watch import DROPPED, HANDSHAKE_REFUSED, RECONNECTED, UP, LinkChange
from capture_agent.recorder import status as recorder_status
from capture_agent.recorder.disk import DiskBudget
from capture_agent.recorder.intake import CameraTable, log_due
from capture_agent.recorder.links import AgentLinks, receive_hwm
from capture_agent.recorder.recording import Recording
from capture_agent.recorder.sealing import load_recipients
from capture_agent.recorder.start import StartRefused, start_take
from capture_agent.recorder.take import StopLimits, TakeState, drain_to_stop
from protocol.command import command_parser
from protocol.formats.rig_config import AgentEndpoint, RigConfig
from protocol.os_thread import NamedThread
from protocol.safe_text import brief
from protocol.session import EventKind, SessionWriteError
from protocol.wire import ControlRequest, FrameMessage

log = logging.getLogger(__name__)

STALL_LIMIT_S = 20.0  # the I/O loop without progress for this long: exit, systemd restarts
# read at each use (tests shorten them): the parts get them as arguments
WRITE_FAILURE_STOP_S = 5.0  # a take whose file cannot be written for this long is stopped
STOP_WRITE_S = 3.0  # at a stop, write the queued frames of the take for at most this long
STOP_COUNT_S = 1.0  # then count (without writing) what is still queued, for at most this long
STOP_IDLE_S = 0.25  # a stop stops waiting for frames after this long without a message
# what a take records of its links (a new socket is only logged and counted: the failure that
# led to it is the event)
LINK_EVENT_KINDS = {
    DROPPED: EventKind.LINK_DROPPED,
    HANDSHAKE_REFUSED: EventKind.HANDSHAKE_FAILED,
    RECONNECTED: EventKind.LINK_RECONNECTED,
    UP: EventKind.LINK_RECONNECTED,  # an agent first heard mid-take
}


class Recorder:
    def __init__(self, config: RigConfig) -> None:
        self.config = config
        # public keys only, loaded now: a bad key file stops the recorder, not a take
        self.recipients = load_recipients(config.sealing, f"recorder {config.rig_name}")
        self.table = CameraTable(config)
        self.links = AgentLinks(config)
        self.disk = DiskBudget(output_dir=config.output_dir, reserve_gb=config.disk_reserve_gb)
        self.take = TakeState(config.output_dir)
        self.progress = Progress("io")  # the I/O loop's heartbeat, for status and systemd
        self.internal_errors = 0  # bugs met while handling a message or a periodic step
        self.control = ControlServer(f"recorder {config.rig_name}", self._handle)
        self.stopped = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        self.take.load_resume()  # owner-only session folder; a take to resume (take_journal)
        self.links.open()
        self._thread = NamedThread(target=self._loop, name="recorder-io", daemon=True)
        self._thread.start()
        log.info(
            "recorder %s: %d agent(s), control on %s, sessions in %s",
            self.config.rig_name,
            len(self.config.agents),
            self.config.control_bind,
            self.config.output_dir,
        )

    def stop(self) -> None:
        self.stopped.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    def alive(self) -> bool:
        """Whether the I/O thread runs (systemd's health check)."""
        return self._thread is not None and self._thread.is_alive()

    # -- the I/O loop ---------------------------------------------------------------------------
    def _poller(self) -> zmq.Poller:
        poller = zmq.Poller()
        for sub in self.links.subs:
            poller.register(sub, zmq.POLLIN)
        poller.register(self.links.rep, zmq.POLLIN)
        return poller

    def _loop(self) -> None:
        poller, generation = self._poller(), self.links.generation
        try:
            while not self.stopped.is_set():
                if generation != self.links.generation:  # an agent's SUB socket was made again
                    poller, generation = self._poller(), self.links.generation
                events = dict(poller.poll(20))
                self._receive([s for s in self.links.subs if s in events])
                self.progress.beat("io")
                if self.links.rep in events:
                    self.control.serve(self.links.rep)  # one reply per request, whatever it holds
                try:
                    self.periodic()
                except Exception:
                    self._internal_error("in the periodic step")
        finally:
            if self.take.recording is not None:
                self.stop_recording("the recorder was shut down")
            self.links.close()

    def receive_published(self, timeout_ms: int, max_messages: int = 256) -> int:
        """Wait up to ``timeout_ms`` for messages from any agent, then handle up to
        ``max_messages`` of each agent's; returns how many were handled."""
        poller = zmq.Poller()
        for sub in self.links.subs:
            poller.register(sub, zmq.POLLIN)
        ready = [s for s, _ in poller.poll(timeout_ms)]
        return self._receive(ready, max_messages)

    def _receive(self, ready: list, max_messages: int = 256) -> int:
        """Drain the ready SUB sockets, at most ``max_messages`` each, so that control and
        flushing come back regularly."""
        n = 0
        for sub in ready:
            agent = self.links.subs[sub]
            for _ in range(max_messages):
                try:
                    parts = sub.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                n += 1
                try:
                    self.on_published(parts, agent)
                except Exception:  # one message's bug must not end the take or the loop
                    self._internal_error("handling a message from agent " + agent.node_id)
        return n

    def on_published(self, parts: list, agent: AgentEndpoint) -> None:
        """A message from ``agent``'s SUB socket: a frame the camera table accepts goes to the
        take; no message is kept after it is handled."""
        rx_ns = time.time_ns()
        msg = self.table.decode(parts, agent)
        if msg is not None:
            self.on_frame(msg, rx_ns)

    def on_frame(self, msg: FrameMessage, rx_ns: int) -> None:
        # The console's preview subscribes to the agent itself (rig_client.last_frame): each
        # message pins its images (up to 128 MiB).
        if self.table.accept_frame(msg, rx_ns) and self.take.recording is not None:
            self.take.recording.write_frame(msg, rx_ns)

    def _internal_error(self, what: str) -> None:
        """Count and log (rate-limited, with the traceback) an unexpected exception."""
        self.internal_errors += 1
        if log_due(self.internal_errors):
            log.exception("internal error #%d %s; the recorder goes on", self.internal_errors, what)

    def watch_links(self) -> None:
        """Links that dropped, were refused or came back: counted (``links``), recorded in the
        take; a socket whose retry is due is drained, then made again."""
        for agent, change in self.links.check():
            self._link_event(agent, change)
        for sub in self.links.due():
            # what the old socket still queues is the agent's, received before the drop
            self._receive([sub], receive_hwm(self.config, self.links.subs[sub]))
            self._link_event(*self.links.recreate(sub))

    def _link_event(self, agent: AgentEndpoint, change: LinkChange) -> None:
        kind = LINK_EVENT_KINDS.get(change.kind)
        if kind is not None and self.take.recording is not None:
            self.take.recording.append_event(kind, agent.node_id, detail=change.cause)

    def periodic(self) -> None:
        """Between messages: the links, a take to resume, flushes, write failures, the disk
        check."""
        self.watch_links()
        resume_args = self.take.resume_now(self.table)  # never waits
        if resume_args is not None:
            self._resume(resume_args)
        now = time.monotonic()
        rec = self.take.recording
        if rec is not None:
            rec.poll(time.time_ns())
            if now - rec.last_flush >= self.config.flush_interval_s:
                rec.request_flush()  # queued behind the frames; never waits for the disk
            if (
                rec.write_failing_since is not None
                and rec.write_failing_s() >= WRITE_FAILURE_STOP_S
            ):
                self.stop_recording(
                    f"writing {rec.writer.path} failed for {rec.write_failing_s():.0f} s "
                    f"({rec.write_error}); stopped. The file holds what was written before; "
                    "check the disk, then start a new recording",
                    write_queued=False,
                )
                return
        # Stop while there is still room for what arrives before the next checks and for
        # closing the file: the reserve stays untouched.
        if (
            self.disk.check_due(now)
            and rec is not None
            and self.disk.near_reserve(self._take_rate(rec, now))
        ):
            log.error("disk space under the reserve: stopping the recording cleanly")
            self.stop_recording(
                f"the disk holding {self.config.output_dir} came within a few seconds of the "
                f"reserve of {self.config.disk_reserve_gb:g} GB; stopped before it filled",
                write_queued=False,
            )

    def _take_rate(self, rec: Recording, now: float) -> float:
        """The take's bytes/s: the cameras' configured rate x their typical frame, or the
        sustained write rate if higher; never a burst's (``Recording.take_rate_bytes_per_s``)."""
        return rec.take_rate_bytes_per_s(now)

    def _resume(self, args: dict[str, Any]) -> None:
        """Start the take a killed recorder left (``TakeState.resume_now`` said so)."""
        try:
            self._start(args)
        except (Refused, SessionWriteError) as exc:
            self.take.resume_refused(exc)
        except Exception as exc:  # a bug must not take the I/O loop down
            self.take.resume_failed(exc)

    # -- control --------------------------------------------------------------------------------
    def _handle(self, req: ControlRequest) -> dict[str, Any]:
        if req.verb == "heartbeat":
            return {"rig_name": self.config.rig_name, "unix_ns": time.time_ns()}
        if req.verb == "status":
            return self.status()
        if req.verb == "start":
            return self._start(req.args)
        if req.verb == "stop":
            if self.take.recording is None:
                raise StartRefused("not recording; nothing to stop")
            return self.stop_recording("stopped by request")
        raise Refused(f"the recorder does not know the verb {brief(req.verb)}")

    def _start(self, args: dict[str, Any]) -> dict[str, Any]:
        return start_take(
            args,
            config=self.config,
            table=self.table,
            disk=self.disk,
            links=self.links,
            take=self.take,
            recipients=self.recipients,
        )

    def stop_recording(self, reason: str, *, write_queued: bool = True) -> dict[str, Any]:
        """End the take: drain what it still has queued, close it, keep its summary."""
        rec = self.take.recording
        assert rec is not None
        limits = StopLimits(write_s=STOP_WRITE_S, count_s=STOP_COUNT_S, idle_s=STOP_IDLE_S)
        drain_to_stop(
            rec,
            {s for s in rec.serials if self.table.is_streaming(s)},
            self.receive_published,
            write=write_queued,
            flush_interval_s=self.config.flush_interval_s,
            limits=limits,
        )
        counts = {
            "malformed_messages": self.table.malformed,
            "unknown_version_messages": self.table.unknown_version,
        }
        return self.take.finish(reason, counts, limits)

    # -- the report -----------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        rec = self.take.recording
        loop = {
            "control": self.control.counts(),
            "progress_age_s": self.progress.ages_s(),
            "internal_errors": self.internal_errors + (rec.queue.internal_errors if rec else 0),
            "stall_limit_s": STALL_LIMIT_S,
        }
        return recorder_status.status(self.table, self.links, self.disk, self.take, loop)

    def status_line(self) -> str:
        """One line for systemd's ``STATUS=`` (read from another thread: plain reads only)."""
        return recorder_status.status_line(self.table, self.take.recording)


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
        healthy=recorder.alive,
    )
