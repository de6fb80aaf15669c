"""What every wire message shares: the errors, the binary prefix, the version rule, buffer
views without copies, and the checks of JSON fields. The spec is ``protocol/wire/__init__.py``'s
docstring; each message kind has its own module beside this one."""

from __future__ import annotations

import dataclasses
import json
import struct
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from protocol.errors import UserError
from protocol.safe_text import brief as _brief

if TYPE_CHECKING:
    import zmq


class MalformedMessageError(UserError, ValueError):
    """A message that does not follow the wire spec in ``protocol/wire/__init__.py``'s docstring."""


class UnknownVersionError(MalformedMessageError):
    """A well-formed EgoSurg message of a wire version this code does not speak."""


# The magics live here, not in their kinds' modules: a receiver names the kind it got instead.
FRAME_MAGIC = b"EGSF"
STATUS_MAGIC = b"EGSH"

MAX_JSON_BYTES = 1024 * 1024  # status and control bodies
MAX_NODE_ID_BYTES = 32

PREFIX = struct.Struct("<4sH")  # magic + version, shared by both binary message kinds
U63 = 2**63  # unsigned wire integers stay below this so they fit an int64
I64_MIN, I64_MAX = -(2**63), 2**63 - 1

# What an image buffer may be when a message is built. After construction it is ``bytes`` (kept
# as given) or a flat unsigned-byte ``memoryview`` over the caller's memory: never a copy.
ImageBuffer: TypeAlias = "bytes | bytearray | memoryview | np.ndarray"
# One received part: bytes, a buffer, or a ``zmq.Frame`` from ``recv_multipart(copy=False)``.
WirePart: TypeAlias = "bytes | bytearray | memoryview | np.ndarray | zmq.Frame"


# --------------------------------------------------------------------------------------------
# Buffers, prefix and version
# --------------------------------------------------------------------------------------------


def flat_bytes(buf: object, what: str) -> memoryview:
    """A 1-D unsigned-byte view of ``buf`` without copying; rejects non-buffers."""
    try:
        view = memoryview(buf)  # type: ignore[arg-type]
    except TypeError:
        raise MalformedMessageError(
            f"{what} is a {type(buf).__name__}, expected bytes or a buffer (memoryview, numpy)"
        ) from None
    if not view.c_contiguous:
        raise MalformedMessageError(
            f"{what} is not C-contiguous; pass np.ascontiguousarray(image) so it can be sent as is"
        )
    return view if view.format == "B" and view.ndim == 1 else view.cast("B")


def as_buffer(part: object, what: str) -> bytes | memoryview:
    """A received part as ``bytes`` or a flat byte view; ``zmq.Frame`` via ``.buffer``."""
    if isinstance(part, bytes):
        return part
    if not isinstance(part, bytearray | memoryview) and hasattr(part, "buffer"):
        part = part.buffer  # zmq.Frame: a view of the message memory, not a copy
    return flat_bytes(part, what)


def check_prefix(buf: bytes | memoryview, magic: bytes, supported: int, kind: str) -> None:
    if len(buf) < PREFIX.size:
        raise MalformedMessageError(
            f"{kind} message first part is {len(buf)} bytes, too short to hold the "
            f"{PREFIX.size}-byte magic and version (truncated)"
        )
    got_magic, version = PREFIX.unpack_from(buf)
    if got_magic != magic:
        raise MalformedMessageError(_magic_problem(got_magic, f"{kind} message", magic))
    check_version(version, supported, f"{kind} message")


def _magic_problem(got: bytes, kind: str, expected: bytes) -> str:
    other = {FRAME_MAGIC: "a frame message", STATUS_MAGIC: "an agent status message"}.get(got)
    if other is not None:
        return (
            f"header magic {_brief(got)} is {other}, not a {kind}; decode with decode_published()"
        )
    return (
        f"header magic {_brief(got)} is not an EgoSurg message (a {kind} starts with {expected!r})"
    )


def check_version(version: object, supported: int, kind: str) -> None:
    if version == supported:
        return
    if isinstance(version, int) and not isinstance(version, bool) and version > supported:
        hint = "upgrade the receiver (recorder or control tool) to the sender's EgoSurg version"
    else:
        hint = (
            "upgrade the sender (capture agent or control tool) to the receiver's EgoSurg version"
        )
    raise UnknownVersionError(
        f"{kind} wire version {_brief(version)} is not supported by this receiver "
        f"(supports {supported}); {hint}"
    )


def check_int(value: object, what: str, lo: int, hi: int) -> int:
    """``value`` as a plain ``int`` if it is an integer in ``lo..hi``; bools are not integers."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise MalformedMessageError(f"{what}={_brief(value)} must be an integer")
    number = int(value)
    if lo == 0 and number < 0:
        raise MalformedMessageError(f"{what}={number} must not be negative")
    if not lo <= number <= hi:
        raise MalformedMessageError(f"{what}={number} is outside {lo}..{hi}")
    return number


def check_node_id(node_id: object, what: str) -> None:
    if not isinstance(node_id, str):
        raise MalformedMessageError(f"{what} node_id={_brief(node_id)} must be a string")
    try:
        raw = node_id.encode("utf-8")
    except UnicodeEncodeError:
        raise MalformedMessageError(
            f"{what} node_id={_brief(node_id)} cannot be encoded as UTF-8"
        ) from None
    if not 1 <= len(raw) <= MAX_NODE_ID_BYTES or "\0" in node_id:
        raise MalformedMessageError(
            f"{what} node_id={_brief(node_id)} must be 1..{MAX_NODE_ID_BYTES} UTF-8 bytes "
            "without NUL "
            f"(it is {len(raw)} bytes)"
        )


def check_choice(value: object, what: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise MalformedMessageError(
            f"{what} {_brief(value)} is unknown; valid: {', '.join(choices)}"
        )


def check_json_object(value: object, what: str) -> None:
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise MalformedMessageError(
            f"{what} must be a JSON object with string keys, got {_brief(value)}"
        )
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise MalformedMessageError(f"{what} cannot be sent as JSON: {exc}") from None


_JSON_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", bool: "true/false",
                    dict: "an object", list: "a list"}  # fmt: skip


def json_field(
    d: Mapping[str, Any], key: str, kind: type, where: str, *, nullable: bool = False
) -> Any:
    """``d[key]`` checked against a JSON type; missing keys are errors, extra keys are ignored."""
    if key not in d:
        raise MalformedMessageError(f"{where}: missing field {_brief(key)}")
    value = d[key]
    if value is None and nullable:
        return None
    if kind is float:  # JSON does not tell 30 from 30.0
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if not ok:
        expected = _JSON_TYPE_NAMES[kind] + (" or null" if nullable else "")
        raise MalformedMessageError(
            f"{where}: field {_brief(key)}={_brief(value)} must be {expected}"
        )
    return value


def check_nullable(value: object, kind: type, what: str, expected: str) -> None:
    """Raise unless ``value`` is None or a ``kind``; ``expected`` says both in words."""
    if value is not None and not isinstance(value, kind):
        raise MalformedMessageError(f"{what}={_brief(value)} must be {expected}")


def require_object(obj: object, where: str) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise MalformedMessageError(f"{where} must be a JSON object, got {type(obj).__name__}")
    return obj


def fields_json(record: Any) -> dict[str, Any]:
    """A flat record's JSON object: each dataclass field by its name, in declaration order (the
    order the spec lists them in), so a field added to the record is also on the wire."""
    return {f.name: getattr(record, f.name) for f in dataclasses.fields(record)}


def dump_json(obj: dict[str, Any], what: str) -> bytes:
    body = json.dumps(obj, allow_nan=False, ensure_ascii=False, separators=(",", ":"))
    data = body.encode("utf-8")
    if len(data) > MAX_JSON_BYTES:
        raise MalformedMessageError(
            f"{what} JSON is {len(data)} bytes, above the {MAX_JSON_BYTES}-byte limit"
        )
    return data


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not valid JSON")


def load_json_object(buf: bytes | memoryview, what: str) -> dict[str, Any]:
    if len(buf) > MAX_JSON_BYTES:
        raise MalformedMessageError(
            f"{what} JSON is {len(buf)} bytes, above the {MAX_JSON_BYTES}-byte limit"
        )
    try:
        text = bytes(buf).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MalformedMessageError(f"{what} body is not UTF-8 ({exc.reason})") from None
    try:
        obj = json.loads(text, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        raise MalformedMessageError(f"{what} body is not valid JSON: {exc}") from None
    if "\\u" in text:  # a "\ud800" escape decodes to a lone surrogate that cannot be re-sent
        try:
            json.dumps(obj, ensure_ascii=False).encode("utf-8")
        except (UnicodeEncodeError, RecursionError):
            raise MalformedMessageError(
                f"{what} body holds an unpaired UTF-16 surrogate escape (like \\ud800), "
                "which is not text"
            ) from None
    if not isinstance(obj, dict):
        raise MalformedMessageError(
            f"{what} body is a JSON {type(obj).__name__}, expected a JSON object"
        )
    return obj
