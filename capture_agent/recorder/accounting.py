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

Totals per camera (``CameraTotals``): ``frames_missing`` = the sum of index gaps,
``= frames_dropped_camera + transport_lost``; ``time_gaps`` and ``reconnects`` count events.
``transport_lost_by_node()`` gives every lost message per node, attributed or not.
"""

from __future__ import annotations

import logging
from bisect import bisect_left, insort
from collections import deque
from dataclasses import dataclass

from protocol.session import GapKind, GapRecord

log = logging.getLogger(__name__)

NO_FRAME_INDEX = -1  # first_missing_frame_index of a SEQ_GAP, or of a RECONNECT that reset
TIME_GAP_FACTOR = 1.5  # a gap is an interval above 1.5x the median (docs/session.md, Gap kinds)
MEDIAN_WINDOW = 31  # per-frame intervals in the running median
MEDIAN_MIN_SAMPLES = 3  # no time gap is judged before this many intervals
MAX_LOST_RANGES = 1024  # per node; older ranges become unattributed


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

    def __init__(self) -> None:
        self._nodes: dict[str, _Node] = {}
        self._cams: dict[int, _Camera] = {}

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
        if node.last_seq is not None:
            if seq > node.last_seq + 1:
                first_lost = node.last_seq + 1
                lost = seq - first_lost
                node.lost += lost
                node.ranges.append(_LostRange(first_lost, seq - 1))
                while len(node.ranges) > MAX_LOST_RANGES:
                    node.ranges.popleft()
                out.append(
                    gap_record(
                        serial, GapKind.SEQ_GAP, NO_FRAME_INDEX, lost, node.last_capture_ns, cap
                    )
                )
                log.warning("node %s: %d frame messages lost in transport", node_id, lost)
            elif seq <= node.last_seq:
                node.epoch += 1
                node.ranges.clear()
                log.info(
                    "node %s: seq went from %d to %d: agent restarted", node_id, node.last_seq, seq
                )
        node.last_seq, node.last_capture_ns = seq, cap

        cam = self._cams.get(serial)
        if cam is None:
            cam = self._cams[serial] = _Camera(node_id, node.epoch)
            self._remember(cam, idx, seq, cap)
            return out
        if cam.node_id != node_id or cam.epoch != node.epoch or idx <= cam.index:
            skipped = idx - cam.index - 1
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
            cam.missing += n
            cam.transport += by_transport
            cam.dropped += n - by_transport
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
