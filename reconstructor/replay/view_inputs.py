"""The values ``egosurg view``'s page may send for its controls, checked before viser stores them.

Viser stores whatever a browser's GuiUpdateMessage says, for any property of a control (its
value, but also its min, max, label or options), and sends it on to every other browser and to
every browser that connects later. One value its encoder cannot write (a slider set to 1e308
becomes an integer of 309 digits) broke the page for every browser until the viewer was
restarted. The page itself only ever sends a control's ``value``, inside the control's limits,
so that is all that passes here:

- a property other than ``value`` is refused (the page never sends one);
- a slider or number: a finite number (not a bool), clamped to its min and max and put on its
  step; an integer control gets an integer;
- a dropdown or button group: one of its options; text: a string of at most
  ``MAX_TEXT_CHARS``; a checkbox or button: a bool;
- any other kind of control (this page has none) is refused.

A refused update is dropped and a clamped one passed on as clamped, each with a warning line
(counted, so that a page that repeats itself does not flood the log).
"""

from __future__ import annotations

import logging
import math
from typing import Any

log = logging.getLogger(__name__)

MAX_TEXT_CHARS = 1000  # longer than any label or name a reviewer types into this page
_SHOWN_CHARS = 60  # how much of a refused value a log line quotes


class RareWarnings:
    """Warnings counted per kind and logged at the 1st, 10th, 100th, ... of each: a page that
    retries every second is visible in the log without filling it."""

    def __init__(self, logger: logging.Logger) -> None:
        self._log = logger
        self.counts: dict[str, int] = {}

    def warn(self, kind: str, message: str, *args: object) -> None:
        n = self.counts[kind] = self.counts.get(kind, 0) + 1
        if math.log10(n).is_integer():
            self._log.warning(message + " (%d so far)", *args, n)


def shown(value: object) -> str:
    """A value as a log line may quote it: its repr, cut short."""
    text = repr(value)
    return text if len(text) <= _SHOWN_CHARS else f"{text[:_SHOWN_CHARS]}... ({len(text)} chars)"


def clean_value(props: Any, current: Any, value: Any) -> Any:
    """``value`` as the control with ``props`` (viser's props record) and ``current`` value may
    hold it: clamped to its limits; ``ValueError`` (naming why) when it cannot hold it."""
    if isinstance(current, bool):  # checkbox, button; before int: a bool is an int
        if not isinstance(value, bool):
            raise ValueError("not true or false")
        return value
    if isinstance(current, (int, float)):
        return _clean_number(props, current, value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ValueError("not a string")
        options = getattr(props, "options", None)
        if options is not None:
            if value not in options:
                raise ValueError("not one of the control's options")
            return value
        if len(value) > MAX_TEXT_CHARS:
            raise ValueError(f"longer than {MAX_TEXT_CHARS} characters")
        return value
    raise ValueError(f"a {type(current).__name__} control, which this viewer does not check")


def _clean_number(props: Any, current: int | float, value: Any) -> int | float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError("not a number")
    v = float(value)  # an int past float's range becomes inf, refused next
    if not math.isfinite(v):
        raise ValueError("not a finite number")
    lo, hi = getattr(props, "min", None), getattr(props, "max", None)
    step = getattr(props, "step", None)
    # into the limits first: 1e308 over a step of 0.001 has no whole number of steps
    v = _clamp(v, lo, hi)
    if step:  # onto the control's grid, counted from its minimum
        origin = float(lo) if lo is not None else 0.0
        v = _clamp(origin + round((v - origin) / float(step)) * float(step), lo, hi)
    return round(v) if isinstance(current, int) else v


def _clamp(v: float, lo: float | None, hi: float | None) -> float:
    if lo is not None:
        v = max(v, float(lo))
    if hi is not None:
        v = min(v, float(hi))
    return v


def clean_updates(label: str, props: Any, current: Any, updates: dict[str, Any]) -> dict:
    """The updates a browser sent for one control, as viser may store them; ``ValueError``
    (one line naming the control and the reason) when they cannot be."""
    extra = sorted(set(updates) - {"value"})
    if extra:
        raise ValueError(f"{label!r}: the page never sends {shown(extra)}")
    if "value" not in updates:
        raise ValueError(f"{label!r}: no value")
    value = updates["value"]
    try:
        return {"value": clean_value(props, current, value)}
    except ValueError as exc:
        raise ValueError(f"{label!r} = {shown(value)}: {exc}") from None
