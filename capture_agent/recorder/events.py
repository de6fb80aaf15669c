"""Session events as the recording writes them (``/events``, ``docs/session.md``): what happened
to the links and the streams during a take, each with the node (and camera) it concerns.

Why a limiter. Events come from what the nodes send and from the links' state, so a broken or
hostile node could raise one per message: thousands a second. ``EventLimiter`` writes at most
``ROWS_PER_WINDOW`` rows per kind and node in each ``WINDOW_S``; the occurrences past that are
held and written as one row whose ``count`` says how many it stands for, when the window ends
(the next event of that kind and node, the recording's next poll, or the take's end). So the
file holds every occurrence, counted, in at most (``ROWS_PER_WINDOW`` + 1) rows per kind, node
and second; the nodes and kinds are bounded (rig.toml's agents, ``EventKind``), and so are the
limiter's keys (``MAX_KEYS``; past it, new keys share one).
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol.session import EventKind

ROWS_PER_WINDOW = 5  # rows per kind and node in each window, each for one occurrence
WINDOW_S = 1.0
MAX_KEYS = 256  # kinds x nodes; rig.toml's agents keep it far below
OVERFLOW_NODE = "*"  # the node of events whose own key did not fit under MAX_KEYS


@dataclass(frozen=True, kw_only=True, slots=True)
class EventRow:
    """A row to write: ``SessionWriter.append_event``'s arguments."""

    kind: EventKind
    time_unix_ns: int
    node_id: str
    camera_serial: int
    count: int
    detail: str


class _Window:
    __slots__ = ("held", "held_detail", "held_serial", "held_since_ns", "rows", "start_s")

    def __init__(self, start_s: float) -> None:
        self.start_s = start_s
        self.rows = 0  # rows written in this window
        self.held = 0  # occurrences past them, not yet written
        self.held_serial = -1
        self.held_detail = ""
        self.held_since_ns = 0


class EventLimiter:
    """Turns occurrences into rows, at most ``ROWS_PER_WINDOW`` (+1 aggregate) per kind, node
    and ``WINDOW_S``. Times: ``now_s`` monotonic seconds, ``now_ns`` the unix time stored."""

    def __init__(self, *, rows_per_window: int = ROWS_PER_WINDOW, window_s: float = WINDOW_S):
        if rows_per_window < 1 or not window_s > 0:
            raise ValueError(
                f"rows_per_window must be >= 1 and window_s > 0, got {rows_per_window}, {window_s}"
            )
        self.rows_per_window = rows_per_window
        self.window_s = window_s
        self._windows: dict[tuple[EventKind, str], _Window] = {}
        self.occurrences = 0  # every occurrence admitted, written or held

    def admit(
        self,
        kind: EventKind,
        node_id: str,
        camera_serial: int,
        detail: str,
        *,
        now_s: float,
        now_ns: int,
    ) -> list[EventRow]:
        """One occurrence: the rows to write now (none while it is held for an aggregate)."""
        self.occurrences += 1
        key = (kind, node_id)
        if key not in self._windows and len(self._windows) >= MAX_KEYS:
            key = (kind, OVERFLOW_NODE)
        out: list[EventRow] = []
        w = self._windows.get(key)
        if w is not None and now_s - w.start_s >= self.window_s:
            out += self._release(key, w, now_ns)
            w = None
        if w is None:
            w = self._windows[key] = _Window(now_s)
        if w.rows < self.rows_per_window:
            w.rows += 1
            out.append(
                EventRow(
                    kind=kind,
                    time_unix_ns=now_ns,
                    node_id=key[1],
                    camera_serial=camera_serial,
                    count=1,
                    detail=detail,
                )
            )
            return out
        if w.held == 0:
            w.held_since_ns, w.held_serial = now_ns, camera_serial
        elif w.held_serial != camera_serial:
            w.held_serial = -1  # several cameras of the node
        w.held += 1
        w.held_detail = detail
        return out

    def due(self, *, now_s: float, now_ns: int) -> list[EventRow]:
        """The aggregates of the windows that ended (and forget idle windows)."""
        out: list[EventRow] = []
        for key, w in list(self._windows.items()):
            if now_s - w.start_s >= self.window_s:
                out += self._release(key, w, now_ns)
                del self._windows[key]
        return out

    def drain(self, *, now_ns: int) -> list[EventRow]:
        """Every held aggregate (the take ends)."""
        out: list[EventRow] = []
        for key, w in list(self._windows.items()):
            out += self._release(key, w, now_ns)
        self._windows.clear()
        return out

    @staticmethod
    def _release(key: tuple[EventKind, str], w: _Window, now_ns: int) -> list[EventRow]:
        if w.held == 0:
            return []
        row = EventRow(
            kind=key[0],
            time_unix_ns=w.held_since_ns,
            node_id=key[1],
            camera_serial=w.held_serial,
            count=w.held,
            detail=f"{w.held} more in {(now_ns - w.held_since_ns) / 1e9:.1f} s; the last: "
            + w.held_detail,
        )
        w.held = 0
        return [row]
