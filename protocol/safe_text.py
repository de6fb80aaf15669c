r"""Text from the network, made safe to print and bounded before it is quoted.

A node id, a case name or an error from a peer may carry terminal escapes (``ESC [ 2 J`` clears
the operator's screen), C1 controls or bidirectional overrides (U+202E shows ``exe.txt`` as
``txt.exe``), and may be megabytes long. Everything that prints remote text (``egosurg status``,
error replies) passes it through ``safe_text``; everything that quotes input in an error message
uses ``brief``, so a reply never echoes unbounded input.

Example::

    safe_text("orin-a\x1b[2J")      # -> orin-a\x1b[2J (a backslash, not an escape)
    brief("\\" * 520_000)           # -> a repr of about 80 characters: start ... end
"""

from __future__ import annotations

import re
import reprlib

BRIEF_CHARS = 80  # how much of an input an error message quotes
# C0 and C1 controls and DEL; the Arabic letter mark; LRM/RLM; line and paragraph separators;
# the bidi embeddings and overrides (U+202A-202E) and isolates (U+2066-2069).
_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028-\u202e\u2066-\u2069]")

_repr = reprlib.Repr()
_repr.maxstring = BRIEF_CHARS
_repr.maxother = BRIEF_CHARS
_repr.maxlong = 40
_repr.maxlist = _repr.maxtuple = _repr.maxdict = _repr.maxset = 6
_repr.maxlevel = 3


def _escape(match: re.Match[str]) -> str:
    code = ord(match.group())
    return f"\\x{code:02x}" if code <= 0xFF else f"\\u{code:04x}"


def unsafe_character(text: str) -> str | None:
    """The first control or bidi character in ``text`` (escaped, e.g. ``\\x1b``), else None."""
    m = _UNSAFE.search(text)
    return None if m is None else _escape(m)


def safe_text(value: object, limit: int | None = None) -> str:
    """``str(value)`` with every control and bidi character escaped (``\\x1b``, ``\\u202e``),
    cut to ``limit`` characters (marked with ``...``) when a limit is given."""
    text = value if isinstance(value, str) else str(value)
    if limit is not None and len(text) > limit:
        text = text[: max(limit - 3, 0)] + "..."
    out = _UNSAFE.sub(_escape, text)
    if limit is not None and len(out) > limit:  # escapes lengthen the text
        out = out[: max(limit - 3, 0)] + "..."
    return out


def brief(value: object, limit: int = BRIEF_CHARS) -> str:
    """A ``repr`` of ``value`` for an error message: bounded (about ``limit`` characters, long
    strings shown by their start and end) and terminal-safe, whatever the value holds."""
    try:
        text = _repr.repr(value)
    except Exception:  # a repr that fails must not turn a refusal into a crash
        text = f"<{type(value).__name__}>"
    return safe_text(text, limit + 8)
