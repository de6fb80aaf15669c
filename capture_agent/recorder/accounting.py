"""Per-camera drop and gap accounting, done by the recorder from the frames it receives.

The SDK's own drop counter is not to be trusted, so the recorder counts
from what it sees: the per-camera ``frame_index``, the per-publisher ``seq`` and the capture stamps.

What each gap kind means
------------------------
- ``FRAME_INDEX_GAP``: a camera's ``frame_index`` skipped ``n`` values. The record names exactly
  which frames of that camera are absent from the recording (``first_missing_frame_index``,
  ``missing_count``), whatever the cause: dropped at the camera or agent (never published), or
  lost in transport (published, then dropped by PUB/SUB at the high-water mark).
- ``SEQ_GAP``: the node's publisher ``seq`` skipped ``n`` values: ``n`` frame messages of that node
  were lost between agent and recorder. ``seq`` is shared by the node's cameras, so the lost
  messages cannot be pinned on a camera when the gap is seen. The record is filed against the
  camera whose frame revealed the gap (the node's first frame after it), with
  ``first_missing_frame_index = NO_FRAME_INDEX``; read it as a node event.
- ``TIME_GAP``: the interval to the previous frame of the camera exceeds 1.5x the running median
  of its per-frame interval. ``missing_count`` is an estimate (frame slots that passed). It is
  reported alongside any index gap that caused it, but it never adds to the drop totals.
- ``RECONNECT``: a new stream: the camera's ``frame_index`` went backwards or repeated (camera
  reopened), the node's ``seq`` went backwards (agent restarted), or the camera now comes from
  another node. No gap is computed across it; ``missing_count`` is the index gap when the index
  continued upwards, else 0 (unknown).

  An implausible jump is a reconnect too: a ``frame_index`` step, or a node's ``seq`` step, of
  more than an hour of frames at the camera's rate (``MAX_PLAUSIBLE_GAP_S`` x fps; for ``seq``,
  times the node's cameras). No camera drops an hour of frames between two frames it delivers
  (the time between them shows such a pause as a ``TIME_GAP``), so such a jump is a restarted,
  buggy or forged counter: counting it as drops would put a made-up number (1e12) into the
  take's totals. It is recorded as ``RECONNECT`` with ``missing_count`` 0 and
  ``first_missing_frame_index`` -1, never added to the totals, and noted (``notes``) for the
  session's events (``IMPLAUSIBLE_JUMP``). A ``seq`` that goes back is noted too
  (``PUBLISHER_CHANGED``): the node's publisher restarted, or another took its place.

Splitting a camera's missing frames into camera drops and transport losses
-------------------------------------------------------------------------
Every lost message is a frame of one of the node's cameras, so it also shows up later as an index
gap of that camera. To count it once, the node keeps its lost ``seq`` ranges. When a camera shows
an index gap of ``n`` frames between its frames with seqs ``s0`` and ``s1``, its lost frames can
only have had seqs in ``(s0, s1)``; up to ``n`` still unclaimed lost seqs in that interval are
claimed as transport losses of this camera, the rest are camera drops. Ranges that no camera of
the node can claim any more are left as the node's unattributed losses. When a camera drop and a
transport loss of two cameras of one node fall between the same frames, the per-camera split can
swap them; the node's sums stay exact.

Frames the recorder refused (a stamp that went back, over the camera's rate or byte cap) are
missing from the file too, so they show as an index gap; ``refused`` tells the accounting of each,
and the camera's next index gap counts up to that many as ``frames_refused``, not as drops. The
node's ``seq`` takes a refused frame's as seen, so a refusal is not a transport loss either.

Totals per camera (``CameraTotals``): ``frames_missing`` = the sum of index gaps,
``= frames_dropped_camera + transport_lost`` + the refused frames before the camera's last frame;
``frames_refused`` counts every refused frame; ``time_gaps`` and ``reconnects`` count events.
``transport_lost_by_node()`` gives every lost message per node, attributed or not.
"""

from __future__ import annotations

import logging
from bisect import bisect_left, insort
from collections import deque
from dataclasses import dataclass

from protocol.session import EventKind, GapKind, GapRecord

log = logging.getLogger(__name__)

NO_FRAME_INDEX = -1  # first_missing_frame_index of a SEQ_GAP, or of a RECONNECT that reset
TIME_GAP_FACTOR = 1.5  # a gap is an interval above 1.5x the median (docs/session.md, Gap kinds)
MEDIAN_WINDOW = 31  # per-frame intervals in the running median
MEDIAN_MIN_SAMPLES = 3  # no time gap is judged before this many intervals
MAX_LOST_RANGES = 1024  # per node; older ranges become unattributed
MAX_PLAUSIBLE_GAP_S = 3600.0  # a counter step over this many seconds of frames is a reconnect
MAX_NOTES = 1024  # notes kept until the recording takes them


def gap_record(
    serial: int, kind: GapKind, first_missing: int, missing: int, start_ns: int, end_ns: int
) -> GapRecord:
    """The session file's gap record (``/gaps``): ``start_ns``/``end_ns`` are the capture stamps
    of the frames received just before and just after the gap (for ``SEQ_GAP``, the node's
    frames around it)."""
    return GapRecord(
        camera_serial=serial,
        kind=kind,
        first_missing_frame_index=first_missing,
        missing_count=missing,
        start_unix_ns=start_ns,
        end_unix_ns=end_ns,
    )


@dataclass(frozen=True, slots=True)
class CameraTotals:
    frames_received: int
    frames_missing: int  # sum of frame_index gaps = frames_dropped_camera + transport_lost
    frames_dropped_camera: int  # never published: dropped at the camera or the agent
    transport_lost: int  # published by the agent, lost before the recorder
    time_gaps: int
    reconnects: int
    frames_refused: int = 0  # refused by the recorder (stamp back, over its caps)


class _LostRange:
    __slots__ = ("first", "last", "remaining")

    def __init__(self, first: int, last: int) -> None:
        self.first, self.last, self.remaining = first, last, last - first + 1


class _Node:
    __slots__ = ("cameras", "epoch", "last_capture_ns", "last_seq", "lost", "ranges")

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self.last_capture_ns = 0
        self.epoch = 0  # +1 at every agent restart
        self.ranges: deque[_LostRange] = deque()
        self.lost = 0
        self.cameras: set[int] = set()


class _Camera:
    __slots__ = (
        "dropped",
        "epoch",
        "index",
        "intervals",
        "last_capture_ns",
        "missing",
        "node_id",
        "received",
        "reconnects",
        "refused",
        "refused_pending",
        "seq",
        "sorted_intervals",
        "time_gaps",
        "transport",
    )

    def __init__(self, node_id: str, epoch: int) -> None:
        self.node_id, self.epoch = node_id, epoch
        self.index = self.seq = self.last_capture_ns = 0
        self.intervals: deque[float] = deque()
        self.sorted_intervals: list[float] = []
        self.received = self.missing = self.dropped = self.transport = 0
        self.time_gaps = self.reconnects = 0
        self.refused = self.refused_pending = 0  # refused: counted; pending: not yet in a gap

    def median_interval(self) -> float | None:
        v, n = self.sorted_intervals, len(self.sorted_intervals)
        if n < MEDIAN_MIN_SAMPLES:
            return None
        return v[n // 2] if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2.0

    def push_interval(self, per_frame_ns: float) -> None:
        self.intervals.append(per_frame_ns)
        insort(self.sorted_intervals, per_frame_ns)
        if len(self.intervals) > MEDIAN_WINDOW:
            old = self.intervals.popleft()
            del self.sorted_intervals[bisect_left(self.sorted_intervals, old)]

    def clear_intervals(self) -> None:
        self.intervals.clear()
        self.sorted_intervals.clear()


class StreamAccounting:
    """Feed every received frame to ``observe`` in arrival order; see the module docstring."""

    def __init__(self, *, fps: float = 120.0) -> None:
        """``fps``: the cameras' configured rate; it sets what jump is implausible."""
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self._nodes: dict[str, _Node] = {}
        self._cams: dict[int, _Camera] = {}
        self.max_step = max(int(MAX_PLAUSIBLE_GAP_S * fps), 1)
        # (kind, node_id, camera serial or -1, detail) for the session's events; the recording
        # takes them after each frame (``take_notes``)
        self.notes: list[tuple[EventKind, str, int, str]] = []

    def take_notes(self) -> list[tuple[EventKind, str, int, str]]:
        """The notes since the last call (implausible jumps), oldest first."""
        notes, self.notes = self.notes, []
        return notes

    def _note(self, kind: EventKind, node_id: str, serial: int, detail: str) -> None:
        if len(self.notes) < MAX_NOTES:
            self.notes.append((kind, node_id, serial, detail))

    def observe(
        self, camera_serial: int, frame_index: int, seq: int, capture_unix_ns: int, node_id: str
    ) -> list[GapRecord]:
        """Account one received frame; return the gaps it reveals (usually none)."""
        serial, idx, seq, cap = int(camera_serial), int(frame_index), int(seq), int(capture_unix_ns)
        out: list[GapRecord] = []
        node = self._nodes.get(node_id)
        if node is None:
            node = self._nodes[node_id] = _Node()
        node.cameras.add(serial)
        out += self._observe_seq(node, node_id, serial, seq, cap)
        node.last_seq, node.last_capture_ns = seq, cap

        cam = self._cams.get(serial)
        if cam is None:
            cam = self._cams[serial] = _Camera(node_id, node.epoch)
            self._remember(cam, idx, seq, cap)
            return out
        implausible = idx - cam.index > self.max_step
        if implausible:
            self._note(
                EventKind.IMPLAUSIBLE_JUMP,
                node_id,
                serial,
                f"frame_index jumped from {cam.index} to {idx}: a reconnect, not dropped frames",
            )
        if cam.node_id != node_id or cam.epoch != node.epoch or idx <= cam.index or implausible:
            skipped = -1 if implausible else idx - cam.index - 1
            out.append(
                gap_record(
                    serial,
                    GapKind.RECONNECT,
                    cam.index + 1 if skipped >= 0 else NO_FRAME_INDEX,
                    max(skipped, 0),
                    cam.last_capture_ns,
                    cap,
                )
            )
            cam.reconnects += 1
            cam.refused_pending = 0
            if cam.node_id != node_id:
                self._nodes[cam.node_id].cameras.discard(serial)
            cam.node_id, cam.epoch = node_id, node.epoch
            cam.clear_intervals()
            self._remember(cam, idx, seq, cap)
            return out

        step = idx - cam.index
        if step > 1:
            n = step - 1
            by_transport = self._claim(node, cam.seq, seq, n)
            by_refusal = min(n - by_transport, cam.refused_pending)
            cam.refused_pending -= by_refusal
            cam.missing += n
            cam.transport += by_transport
            cam.refused += by_refusal
            cam.dropped += n - by_transport - by_refusal
            out.append(
                gap_record(
                    serial, GapKind.FRAME_INDEX_GAP, cam.index + 1, n, cam.last_capture_ns, cap
                )
            )
        interval = cap - cam.last_capture_ns
        median = cam.median_interval()
        if median is not None and interval > TIME_GAP_FACTOR * median:
            cam.time_gaps += 1
            slots = max(round(interval / median) - 1, 0)
            out.append(
                gap_record(serial, GapKind.TIME_GAP, cam.index + 1, slots, cam.last_capture_ns, cap)
            )
        if interval > 0:
            cam.push_interval(interval / step)
        self._remember(cam, idx, seq, cap)
        self._expire(node)
        return out

    def _observe_seq(
        self, node: _Node, node_id: str, serial: int, seq: int, cap: int
    ) -> list[GapRecord]:
        """The node's ``seq`` step: lost messages (a ``SEQ_GAP``), or a new stream (an agent
        restart, or an implausible jump) that makes each of its cameras reconnect."""
        out: list[GapRecord] = []
        if node.last_seq is None:
            return out
        if seq - node.last_seq > self.max_step * max(len(node.cameras), 1):
            self._note(
                EventKind.IMPLAUSIBLE_JUMP,
                node_id,
                serial,
                f"seq jumped from {node.last_seq} to {seq}: a reconnect, not lost messages",
            )
            node.epoch += 1  # a new stream for each of the node's cameras
            node.ranges.clear()
        elif seq > node.last_seq + 1:
            first_lost = node.last_seq + 1
            lost = seq - first_lost
            node.lost += lost
            node.ranges.append(_LostRange(first_lost, seq - 1))
            while len(node.ranges) > MAX_LOST_RANGES:
                node.ranges.popleft()
            out.append(
                gap_record(serial, GapKind.SEQ_GAP, NO_FRAME_INDEX, lost, node.last_capture_ns, cap)
            )
            log.warning("node %s: %d frame messages lost in transport", node_id, lost)
        elif seq <= node.last_seq:
            node.epoch += 1
            node.ranges.clear()
            log.info(
                "node %s: seq went from %d to %d: agent restarted", node_id, node.last_seq, seq
            )
            self._note(
                EventKind.PUBLISHER_CHANGED,
                node_id,
                -1,
                f"seq went from {node.last_seq} to {seq}: the node's publisher restarted or was "
                "replaced; its cameras reconnect",
            )
        return out

    def refused(self, camera_serial: int, seq: int, node_id: str) -> None:
        """A frame the recorder refused: its camera's next index gap counts it as refused, and
        its node's ``seq`` as seen (when it is the next one: a skip before it stays a loss)."""
        cam = self._cams.get(int(camera_serial))
        if cam is not None and cam.node_id == node_id:
            cam.refused_pending += 1
        node = self._nodes.get(node_id)
        if node is not None and node.last_seq is not None and int(seq) == node.last_seq + 1:
            node.last_seq = int(seq)

    def totals(self) -> dict[int, CameraTotals]:
        """Per camera serial, the counts since the first frame received from it."""
        return {
            s: CameraTotals(
                frames_received=c.received,
                frames_missing=c.missing,
                frames_dropped_camera=c.dropped,
                transport_lost=c.transport,
                time_gaps=c.time_gaps,
                reconnects=c.reconnects,
                frames_refused=c.refused + c.refused_pending,
            )
            for s, c in self._cams.items()
        }

    def transport_lost_by_node(self) -> dict[str, int]:
        """Per node, every frame message lost in transport (from ``seq`` gaps)."""
        return {n: node.lost for n, node in self._nodes.items()}

    # -- internals ------------------------------------------------------------------------
    @staticmethod
    def _remember(cam: _Camera, idx: int, seq: int, cap: int) -> None:
        cam.index, cam.seq, cam.last_capture_ns = idx, seq, cap
        cam.received += 1

    @staticmethod
    def _claim(node: _Node, seq_before: int, seq_after: int, wanted: int) -> int:
        """Claim up to ``wanted`` lost seqs strictly between the camera's two frames."""
        got = 0
        for r in node.ranges:
            if got == wanted:
                break
            overlap = min(r.last, seq_after - 1) - max(r.first, seq_before + 1) + 1
            take = min(overlap, r.remaining, wanted - got)
            if take > 0:
                r.remaining -= take
                got += take
        return got

    def _expire(self, node: _Node) -> None:
        """Drop lost ranges that every camera of the node has passed (nothing can claim them)."""
        if not node.ranges:
            return
        current = [self._cams[s] for s in node.cameras if s in self._cams]
        passed = min((c.seq for c in current if c.epoch == node.epoch), default=0)
        while node.ranges and (node.ranges[0].remaining == 0 or node.ranges[0].last < passed):
            node.ranges.popleft()
