"""A config's fields: their types and rules, checked the same way in code and from a file.

A config is a frozen, keyword-only dataclass whose ``__post_init__`` calls ``validate(self)``:
every field is checked against its type (``int``, ``float``, ``bool``, ``str``, a ``Literal`` of
choices, ``X | None``, ``tuple[X, ...]``, an ``Enum`` with a ``parse`` classmethod, a nested
dataclass) and the rule stated once, on the field, with ``option(default, ge=..., must=...)``.
A rule that spans fields raises ``FieldError`` through ``check``. ``protocol/toml_config.py``
reads such configs from TOML and writes them back.

Example::

    @dataclass(frozen=True, kw_only=True)
    class PtpConfig:
        source: Literal["pmc", "none"] = "pmc"
        lock_threshold_ns: int = option(1000, gt=0, must="must be > 0 ns")

        def __post_init__(self) -> None:
            validate(self)

    PtpConfig(lock_threshold_ns=0)   # FieldError: lock_threshold_ns = 0: must be > 0 ns
"""

from __future__ import annotations

import dataclasses
import enum
import types
import typing
from collections.abc import Callable, Iterable
from typing import Any, Literal

from protocol.errors import ConfigError

__all__ = [
    "FieldError",
    "check",
    "checked",
    "choices_text",
    "convert",
    "field_must",
    "file_fields",
    "hints_of",
    "internal",
    "option",
    "union_args",
    "validate",
]

_RULE = "egosurg.toml_config.rule"
_INTERNAL = "egosurg.toml_config.internal"
_MISSING: Any = dataclasses.MISSING


class FieldError(ConfigError):
    """One field's bad value: ``"<field> = <value>: <must>"``; ``read_table`` adds the file and
    the table (and the dotted key of a nested table) where the field was read."""

    def __init__(self, field: str, value: object, must: str) -> None:
        super().__init__(f"{field} = {value!r}: {must}")
        self.field, self.value, self.must = field, value, must


def check(ok: bool, field: str, value: object, must: str) -> None:
    """Raise ``FieldError(field, value, must)`` unless ``ok`` (a rule that spans fields)."""
    if not ok:
        raise FieldError(field, value, must)


@dataclasses.dataclass(frozen=True)
class _Rule:
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    test: Callable[[Any], bool] | None = None
    must: str = ""

    def holds(self, v: Any) -> bool:
        return (
            (self.ge is None or v >= self.ge)
            and (self.gt is None or v > self.gt)
            and (self.le is None or v <= self.le)
            and (self.lt is None or v < self.lt)
            and (self.test is None or bool(self.test(v)))
        )

    def says(self) -> str:
        if self.must:
            return self.must
        low = f">= {self.ge:g}" if self.ge is not None else f"> {self.gt:g}"
        high = f"<= {self.le:g}" if self.le is not None else f"< {self.lt:g}"
        if self.ge is not None and self.le is not None:
            return f"must be from {self.ge:g} to {self.le:g}"
        has_low = self.ge is not None or self.gt is not None
        has_high = self.le is not None or self.lt is not None
        if has_low and has_high:
            return f"must be {low} and {high}"
        return f"must be {low if has_low else high}"


def option(
    default: Any = _MISSING,
    *,
    factory: Any = _MISSING,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    test: Callable[[Any], bool] | None = None,
    must: str = "",
) -> Any:
    """A field with its rule: a range (``ge``/``gt``/``le``/``lt``) and/or a ``test``; ``must``
    says what the value must be in errors (default: the range). ``None`` is never range-checked
    (an optional field left out)."""
    rule = _Rule(ge=ge, gt=gt, le=le, lt=lt, test=test, must=must)
    return dataclasses.field(default=default, default_factory=factory, metadata={_RULE: rule})


def field_must(f: dataclasses.Field) -> str:
    """What the ``option`` rule of field ``f`` says its value must be ("" without one)."""
    rule = f.metadata.get(_RULE)
    return rule.must if rule is not None else ""


def internal(default: Any = _MISSING, *, factory: Any = _MISSING) -> Any:
    """A field that is not part of the file (where the config came from): not read, not written,
    not checked."""
    return dataclasses.field(
        default=default, default_factory=factory, metadata={_INTERNAL: True}, repr=False
    )


_HINTS: dict[Any, dict[str, Any]] = {}


def hints_of(cls: Any) -> dict[str, Any]:
    """The resolved field types of the dataclass ``cls`` (once per class)."""
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def file_fields(cls: type) -> tuple[dataclasses.Field, ...]:
    return tuple(f for f in dataclasses.fields(cls) if not f.metadata.get(_INTERNAL))


def union_args(hint: Any) -> tuple[Any, ...] | None:
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        return typing.get_args(hint)
    return None


def choices_text(args: Iterable[Any]) -> str:
    return ", ".join(repr(a) for a in args)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def convert(value: Any, hint: Any, field: str) -> Any:
    """``value`` as the type ``hint`` says (int -> float, list -> tuple, a name -> its Enum), or
    ``FieldError`` naming ``field``."""
    union = union_args(hint)
    if union is not None:
        if value is None and type(None) in union:
            return None
        real = [a for a in union if a is not type(None)]
        if len(real) == 1:
            return convert(value, real[0], field)
        if any(isinstance(value, a) for a in real if isinstance(a, type)):
            return value
        raise FieldError(field, value, f"must be one of {', '.join(a.__name__ for a in real)}")
    origin = typing.get_origin(hint)
    if hint is Any or hint is object:
        return value
    if origin is Literal:
        if value not in typing.get_args(hint):
            raise FieldError(field, value, f"choose one of {choices_text(typing.get_args(hint))}")
        return value
    if origin in (tuple, list):
        return _sequence(value, hint, field)
    if origin is dict:
        if not isinstance(value, dict):
            raise FieldError(field, value, "must be a table")
        return value
    return _scalar(value, hint, field)


def _sequence(value: Any, hint: Any, field: str) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if not isinstance(value, list | tuple):
        raise FieldError(field, value, "must be a list")
    if origin is list or (len(args) == 2 and args[1] is Ellipsis):
        items = [convert(v, args[0], f"{field}[{i}]") for i, v in enumerate(value)]
    else:
        if len(value) != len(args):
            raise FieldError(field, value, f"must be a list of {len(args)}")
        items = [
            convert(v, a, f"{field}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        ]
    return items if origin is list else tuple(items)


def _scalar(value: Any, hint: Any, field: str) -> Any:
    if hint is bool:
        if not isinstance(value, bool):
            raise FieldError(field, value, "must be true or false (TOML booleans are unquoted)")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise FieldError(field, value, "must be an integer")
        return value
    if hint is float:
        if not _is_number(value):
            raise FieldError(field, value, "must be a number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise FieldError(field, value, "must be a string")
        return value
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return _enum(value, hint, field)
    if isinstance(hint, type) and not isinstance(value, hint):
        raise FieldError(field, value, f"must be a {hint.__name__}")
    return value


def _enum(value: Any, hint: type[enum.Enum], field: str) -> Any:
    if isinstance(value, hint):
        return value
    parse = getattr(hint, "parse", None)
    try:
        return parse(value) if parse is not None else hint(value)
    except ValueError as exc:
        raise FieldError(field, value, str(exc)) from None


def validate(obj: Any) -> None:
    """Check (and convert in place: int -> float, list -> tuple) every field of the frozen
    dataclass ``obj`` against its type and its ``option`` rule; call it from ``__post_init__``."""
    hints = hints_of(type(obj))
    for f in file_fields(type(obj)):
        value = getattr(obj, f.name)
        new = checked(f, value, hints[f.name], f.name)
        if new is not value:
            object.__setattr__(obj, f.name, new)


def checked(f: dataclasses.Field, value: Any, hint: Any, name: str) -> Any:
    """``value`` of field ``f`` converted to its type ``hint`` and checked against its rule
    (``FieldError`` naming ``name``, the field's dotted key where it was read)."""
    new = convert(value, hint, name)
    rule = f.metadata.get(_RULE)
    if rule is not None and new is not None and not rule.holds(new):
        raise FieldError(name, value, rule.says())
    return new
