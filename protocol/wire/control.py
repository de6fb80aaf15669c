"""Control messages: a ``ControlRequest`` (a verb, its arguments, a request id) answered by one
``ControlReply``, each a UTF-8 JSON object in one part. Spec: ``protocol/wire/__init__.py``."""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from typing import Any, ClassVar

from protocol.safe_text import brief as _brief
from protocol.safe_text import unsafe_character
from protocol.wire.checks import (
    MalformedMessageError,
    WirePart,
    as_buffer,
    check_json_object,
    check_version,
    dump_json,
    json_field,
    load_json_object,
)

CONTROL_WIRE_VERSION = 1
CONTROL_VERBS = ("start", "stop", "status", "heartbeat")
MAX_REQUEST_ID_CHARS = 128  # a uuid4 hex is 32


@dataclass(frozen=True, kw_only=True)
class ControlRequest:
    """A control verb with its arguments, e.g. ``start`` with the session name and case data."""

    verb: str
    args: dict[str, Any] = field(default_factory=dict)
    request_id: str = field(default_factory=lambda: uuid.uuid4().hex)

    __hash__: ClassVar[None] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.verb not in CONTROL_VERBS:
            raise MalformedMessageError(
                f"control verb {_brief(self.verb)} is unknown; valid verbs: "
                f"{', '.join(CONTROL_VERBS)}"
            )
        check_json_object(self.args, "control request args")
        _check_request_id(self.request_id, "control request")

    def to_bytes(self) -> bytes:
        return _encode(self, "control", _REQUEST_FIELDS, "control request")

    @classmethod
    def from_bytes(cls, data: WirePart) -> ControlRequest:
        return cls(**_decode(data, "control", _REQUEST_FIELDS, "control request"))


@dataclass(frozen=True, kw_only=True)
class ControlReply:
    """The answer to one ``ControlRequest``: a result, or an error that says what to do."""

    ok: bool
    result: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    request_id: str

    __hash__: ClassVar[None] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if not isinstance(self.ok, bool):
            raise MalformedMessageError(f"control reply ok={_brief(self.ok)} must be true or false")
        check_json_object(self.result, "control reply result")
        if self.ok and self.error is not None:
            raise MalformedMessageError(
                f"control reply is ok but carries error {_brief(self.error)}; error must be null"
            )
        if not self.ok and (not isinstance(self.error, str) or not self.error.strip()):
            raise MalformedMessageError(
                "control reply is not ok, so error must be a non-empty message saying what to do"
            )
        _check_request_id(self.request_id, "control reply", allow_empty=not self.ok)

    def to_bytes(self) -> bytes:
        return _encode(self, "reply", _REPLY_FIELDS, "control reply")

    @classmethod
    def from_bytes(cls, data: WirePart) -> ControlReply:
        return cls(**_decode(data, "reply", _REPLY_FIELDS, "control reply"))


# Each message's JSON fields after the envelope, in wire order: (name, JSON type, nullable).
_Fields = tuple[tuple[str, type, bool], ...]
_REQUEST_FIELDS: _Fields = (("verb", str, False), ("args", dict, False), ("request_id", str, False))
_REPLY_FIELDS: _Fields = (
    ("ok", bool, False),
    ("result", dict, False),
    ("error", str, True),
    ("request_id", str, False),
)


def _encode(message: ControlRequest | ControlReply, kind: str, fields: _Fields, what: str) -> bytes:
    """The message ``kind`` ("control" or "reply"): the envelope's two fields, then its own."""
    body = {name: getattr(message, name) for name, _, _ in fields}
    return dump_json({"egosurg": kind, "version": CONTROL_WIRE_VERSION, **body}, what)


def _decode(data: WirePart, kind: str, fields: _Fields, what: str) -> dict[str, Any]:
    """The fields of a ``kind`` message, each checked against its JSON type (in wire order, so
    the first bad one is the one named)."""
    d = _load_envelope(data, kind, what)
    return {
        name: json_field(d, name, json_type, what, nullable=nullable)
        for name, json_type, nullable in fields
    }


def _load_envelope(data: WirePart, kind: str, what: str) -> dict[str, Any]:
    d = load_json_object(as_buffer(data, what), what)
    got = d.get("egosurg")
    if got != kind:
        if got in ("control", "reply"):
            raise MalformedMessageError(
                f"{what}: message is an EgoSurg {_brief(got)} message, expected {kind!r}"
            )
        raise MalformedMessageError(
            f"{what}: JSON field 'egosurg' is {_brief(got)}, expected {kind!r}; "
            "this is not an EgoSurg control message"
        )
    if "version" not in d:
        raise MalformedMessageError(f"{what}: missing field 'version'")
    check_version(d["version"], CONTROL_WIRE_VERSION, what)
    return d


def _check_request_id(request_id: object, what: str, *, allow_empty: bool = False) -> None:
    """A request id is 1..MAX_REQUEST_ID_CHARS characters without control characters. Only an
    error reply may carry an empty one: the answer to a request too broken to name its id."""
    if (
        not isinstance(request_id, str)
        or len(request_id) > MAX_REQUEST_ID_CHARS
        or (not request_id and not allow_empty)
        or unsafe_character(request_id) is not None
    ):
        raise MalformedMessageError(
            f"{what} request_id={_brief(request_id)} must be a string of 1..{MAX_REQUEST_ID_CHARS}"
            " characters without control characters"
            + (" (empty only in an error reply to an unreadable request)" if allow_empty else "")
        )


# --------------------------------------------------------------------------------------------
# Shared field checks
# --------------------------------------------------------------------------------------------
