"""``egosurg recorder``: subscribes to every agent of the rig, groups frames into synchronised sets
and writes one HDF5 session per recording.

Example::

    egosurg recorder --config /etc/egosurg/rig.toml

One I/O thread owns every socket and the session file, so control commands (start, stop) are
served in order between frames and two simultaneous starts cannot race. It:

- receives frame messages and agent status on one SUB socket connected to every agent; malformed
  messages and unknown versions are counted, logged and skipped;
- while recording: stores every frame as received (no re-encoding), accounts for drops and gaps
  from frame indices, per-node sequence numbers and timestamps, feeds the synchroniser and stores
  each completed set; flushes the file every ``flush_interval_s`` (a crash loses at most that
  much) and stops cleanly before the disk's free space falls under ``disk_reserve_gb``;
- answers ``start``, ``stop``, ``status`` and ``heartbeat`` on its REP control socket.

The SUB socket queues about ``RECEIVE_QUEUE_S`` of the rig's traffic per agent (its high-water
mark, in messages). A recorder that falls further behind makes the agents' PUB sockets drop
messages, which the per-node ``seq`` shows as transport losses: overload becomes counted loss, not
unbounded memory. At a stop, the take ends at the stop's time: the frames captured before it that
are still queued are received and written first (for up to ``STOP_WRITE_S``), until every
streaming camera has delivered a frame captured after it. Whatever of the take cannot be written
then (the disk reserve was reached, or the queue did not drain in time) is counted per camera as
``not_written_at_stop`` in the stop summary, never dropped silently.

When the session file cannot be written (disk full, I/O error), the take goes on: the writer
keeps what failed and retries it at each flush, frames arriving meanwhile are refused and counted
(``not_written_write_failed``), and ``status`` shows the error. After ``WRITE_FAILURE_STOP_S`` of
failures the take is stopped with the reason; the recorder itself keeps running.

A start is refused, with the reason and what to do, when a camera the rig expects is not
streaming, when an agent's PTP is not locked (``require_ptp_lock``), or when the disk cannot hold
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
from capture_agent.config import RigConfig
from capture_agent.daemon import run_until_signal
from capture_agent.recording import Recording
from capture_agent.sync import SyncConfig, Synchroniser
from protocol import __version__
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
from protocol.session import CameraInfo, SessionWriteError, SessionWriter

log = logging.getLogger(__name__)

CASE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
LIVE_WINDOW_S = 2.0
DISK_CHECK_S = 0.25
DISK_HEADROOM_S = 3.0  # seconds of recording kept free above the reserve
RECEIVE_QUEUE_S = 2.0  # the SUB socket's high-water mark, in seconds of one agent's frames
WRITE_FAILURE_STOP_S = 5.0  # a take whose file cannot be written for this long is stopped
STOP_WRITE_S = 3.0  # at a stop, write the queued frames of the take for at most this long
STOP_COUNT_S = 1.0  # then count (without writing) what is still queued, for at most this long
STOP_IDLE_S = 0.25  # a stop stops waiting for frames after this long without a message


class StartRefused(Exception):
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
    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.ctx: zmq.Context = zmq.Context.instance()
        self.cameras: dict[int, CameraLive] = {}
        self.agent_status: dict[str, tuple[AgentStatus, float]] = {}
        self.recording: Recording | None = None
        self.malformed = 0
        self.unknown_version = 0
        self.stopped = threading.Event()
        self.last_stop_summary: dict[str, Any] | None = None
        self._thread: threading.Thread | None = None
        self._last_disk_check = 0.0
        self._disk_free = self._free_bytes()

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
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
        """The SUB and REP sockets (``start`` calls it; tests drive the I/O by hand)."""
        Path(self.config.output_dir).mkdir(parents=True, exist_ok=True)
        self.sub = self.ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.LINGER, 0)
        self.sub.setsockopt(zmq.RCVHWM, receive_hwm(self.config))
        self.sub.setsockopt(zmq.SUBSCRIBE, b"")
        for a in self.config.agents:
            self.sub.connect(a.frames)
        self.rep = self.ctx.socket(zmq.REP)
        self.rep.setsockopt(zmq.LINGER, 0)
        self.rep.bind(self.config.control_bind)

    def stop(self) -> None:
        self.stopped.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    # -- the I/O loop ---------------------------------------------------------------------------
    def _loop(self) -> None:
        poller = zmq.Poller()
        poller.register(self.sub, zmq.POLLIN)
        poller.register(self.rep, zmq.POLLIN)
        try:
            while not self.stopped.is_set():
                events = dict(poller.poll(20))
                if self.sub in events:
                    # drain what is queued, but come back to control and flushing regularly
                    for _ in range(256):
                        try:
                            parts = self.sub.recv_multipart(zmq.NOBLOCK, copy=False)
                        except zmq.Again:
                            break
                        self._on_published(parts)
                if self.rep in events:
                    self._on_control(self.rep.recv())
                self._periodic()
        finally:
            if self.recording is not None:
                self._stop_recording("the recorder was shut down")
            self.sub.close(linger=0)
            self.rep.close(linger=0)

    def _on_published(self, parts: list) -> None:
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
        if isinstance(msg, AgentStatus):
            self.agent_status[msg.node_id] = (msg, time.monotonic())
            return
        self._on_frame(msg, rx_ns)

    def _on_frame(self, msg: FrameMessage, rx_ns: int) -> None:
        cam = self.cameras.get(msg.camera_serial)
        if cam is None:
            cam = self.cameras[msg.camera_serial] = CameraLive(msg.camera_serial, msg.node_id)
            log.info("camera %d streaming from %s", msg.camera_serial, msg.node_id)
        now = time.monotonic()
        cam.node_id = msg.node_id
        cam.stamps.append(msg.capture_unix_ns)
        cam.rx_monotonic.append(now)
        cam.bytes_rx.append(msg.left_bytes + msg.right_bytes)
        cam.last_rx_monotonic = now
        cam.ptp_offset_ns = msg.ptp_offset_ns
        cam.ptp_locked = msg.ptp_locked
        cam.frames_rx += 1
        cam.last_message = msg  # type: ignore[attr-defined]  # preview for the console
        if self.recording is not None:
            self.recording.write_frame(msg, rx_ns)

    def _periodic(self) -> None:
        now = time.monotonic()
        rec = self.recording
        if rec is not None:
            rec.poll(time.time_ns())
            if now - rec.last_flush >= self.config.flush_interval_s:
                try:
                    rec.flush()
                except SessionWriteError as exc:
                    if rec.write_failing_s() >= WRITE_FAILURE_STOP_S:
                        self._stop_recording(
                            f"writing {rec.writer.path} failed for {rec.write_failing_s():.0f} s "
                            f"({exc}); stopped. The file holds what was written before; check "
                            "the disk, then start a new recording",
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
                rate = max(streams, rec.writer.bytes_written / elapsed)
                headroom = DISK_HEADROOM_S * rate + 8e6
            if rec is not None and self._disk_free < self._reserve_bytes() + headroom:
                log.error("disk space under the reserve: stopping the recording cleanly")
                self._stop_recording(
                    f"the disk holding {self.config.output_dir} came within a few seconds of the "
                    f"reserve of {self.config.disk_reserve_gb:g} GB; stopped before it filled",
                    write_queued=False,
                )

    # -- control --------------------------------------------------------------------------------
    def _on_control(self, raw: bytes) -> None:
        try:
            req = ControlRequest.from_bytes(raw)
        except MalformedMessageError as exc:
            self.rep.send(ControlReply(ok=False, error=str(exc), request_id="").to_bytes())
            return
        try:
            result = self._handle(req)
            reply = ControlReply(ok=True, result=result, request_id=req.request_id)
        except StartRefused as exc:
            reply = ControlReply(ok=False, error=str(exc), request_id=req.request_id)
        except Exception as exc:  # a bug must not take the recorder down mid-case
            log.exception("control %s failed", req.verb)
            reply = ControlReply(
                ok=False, error=f"internal error: {exc}", request_id=req.request_id
            )
        self.rep.send(reply.to_bytes())

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
        raise StartRefused(f"unknown verb {req.verb!r}")

    def _free_bytes(self) -> int:
        target = Path(self.config.output_dir)
        probe = target if target.exists() else target.parent
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        return shutil.disk_usage(probe).free

    def _reserve_bytes(self) -> float:
        return self.config.disk_reserve_gb * 1e9

    def _start_recording(self, args: dict[str, Any]) -> dict[str, Any]:
        if self.recording is not None:
            raise StartRefused(
                f"already recording case '{self.recording.case}' to "
                f"{self.recording.writer.path}; stop it first (egosurg record stop)"
            )
        case = str(args.get("case", ""))
        if not CASE_NAME.match(case):
            raise StartRefused(
                f"case name {case!r} is not usable as a file name; use letters, digits, - _ . "
                "(up to 64 characters)"
            )
        meta = args.get("meta", {})
        if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
            raise StartRefused("case metadata must be key=value text pairs")
        planned_min = float(args.get("planned_duration_min", self.config.planned_duration_min))
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
        writer = SessionWriter(
            path,
            session_name=case,
            case_metadata={str(k): v for k, v in meta.items()},
            cameras=infos,
            tolerance_ns=int(0.5e9 / self.config.fps),
            rig_config_text=self.config.toml_text,
            software_version=__version__,
            started_unix_ns=started_ns,
        )
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
        )
        log.info("recording case %s to %s (%d cameras)", case, path, len(expected))
        return {
            "case": case,
            "file": str(path),
            "cameras": list(expected),
            "started_unix_ns": started_ns,
        }

    def _camera_infos(self, serials: tuple[int, ...]) -> list[CameraInfo]:
        """Ask each agent for its cameras' modes and factory files (stored in the session)."""
        infos: dict[int, CameraInfo] = {}
        for a in self.config.agents:
            reply = self.request_agent(a.control, "status")
            if reply is None:
                if any(
                    self.cameras.get(s) and self.cameras[s].node_id == a.node_id for s in serials
                ):
                    raise StartRefused(
                        f"agent {a.node_id} does not answer on {a.control}; is it running?"
                    )
                continue
            for ci in reply.get("cameras_info", []):
                s = int(ci["camera_serial"])
                infos[s] = CameraInfo(
                    camera_serial=s,
                    node_id=a.node_id,
                    resolution=str(ci["resolution"]),
                    width=int(ci["width"]),
                    height=int(ci["height"]),
                    fps_nominal=float(ci["fps"]),
                    encoding=str(ci["encoding"]),
                    factory_conf_text=str(ci.get("factory_conf", "")),
                )
        missing = [s for s in serials if s not in infos]
        if missing:
            raise StartRefused(
                f"no agent reports camera(s) {missing}; check the serials in rig.toml"
            )
        return [infos[s] for s in serials]

    def request_agent(self, endpoint: str, verb: str, timeout_ms: int = 1500) -> dict | None:
        sock = self.ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVTIMEO, timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, timeout_ms)
        try:
            sock.connect(endpoint)
            sock.send(ControlRequest(verb=verb).to_bytes())
            reply = ControlReply.from_bytes(sock.recv())
            return reply.result if reply.ok else None
        except (zmq.Again, MalformedMessageError):
            return None
        finally:
            sock.close(linger=0)

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
                try:
                    rec.flush()  # a crash while draining loses no more than at any other time
                except SessionWriteError:
                    pass  # counted and reported by the recording
            if not self.sub.poll(int(STOP_IDLE_S * 1000)):
                break
            for _ in range(256):
                try:
                    parts = self.sub.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                self._on_published(parts)
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
        )
        self.recording = None
        self.last_stop_summary = summary
        log.info("stopped case %s: %s", rec.case, reason)
        return summary

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
        }
        if rec is not None:
            out.update(
                {
                    "case": rec.case,
                    "file": str(rec.writer.path),
                    "duration_s": round(time.monotonic() - rec.started_monotonic, 2),
                    "sets": rec.sets_written,
                    "frames": rec.frames_written,
                    "bytes": rec.writer.bytes_written,
                    "capture_to_durable_ms": rec.latency_ms(),
                    "write_failing_s": round(rec.write_failing_s(), 1),
                    "write_error": rec.write_error if rec.write_failing_since else "",
                    "frames_not_written_write_failed": sum(rec.not_written_write_failed.values()),
                }
            )
        if self.last_stop_summary is not None:
            out["last_recording"] = self.last_stop_summary
        return out


def receive_hwm(config: RigConfig) -> int:
    """The SUB socket's high-water mark, in messages: RECEIVE_QUEUE_S of the busiest agent's
    frames (ZeroMQ applies it to each agent's connection), plus its status messages."""
    cameras = max((len(a.cameras) for a in config.agents), default=0) or 4
    return max(100, math.ceil(RECEIVE_QUEUE_S * config.fps * cameras) + 10)


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
        healthy=lambda: recorder._thread is not None and recorder._thread.is_alive(),
    )
