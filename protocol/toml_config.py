"""The one way this house reads a TOML file or table into a frozen dataclass, and writes it back.

A config is a frozen, keyword-only dataclass that checks itself (``protocol/config_fields.py``:
its fields' types and the rule stated once on each field). ``read_table`` builds one from a
parsed table: a ``[table]`` for a nested dataclass, ``[[name]]`` tables for a tuple of dataclasses,
and, for a union of dataclasses, the one whose ``Literal`` tag field matches the table's tag (a
camera's ``source``). An unknown key is refused with the keys that exist (a typo must not fall back
to a default); every error is one ``ConfigError`` line naming the file, the table (the dotted
key), the field and the bad value::

    node.toml: ptp.require_lock = 'yes': must be true or false (TOML booleans are unquoted)
    node.toml: cameras[1].fps = 90: must be > 0 and at most 60 at HD1200 (ZED X: 15, 30, 60)
    node.toml: unknown option 'ptp.treshold'; check the spelling; [ptp] has: source, pmc_path, ...

``dumps`` writes a config back (``tomli-w``): scalars first, then one ``[table]`` per nested
dataclass and ``[[name]]`` per list entry; ``None`` values are left out, so they read back as
the default. Fields made with ``internal()`` (where a config came from) are neither read nor
written.

This module imports nothing heavy (the capture edge imports it) and is the only one that imports
``tomllib`` (``tomli`` before Python 3.11).

Example::

    cfg = read_table(PtpConfig, {"lock_threshold_ns": 500}, "node.toml [ptp]")
    cfg = read_file(PtpConfig, "ptp.toml", "the PTP settings")
    Path("ptp.toml").write_text(dumps(cfg, comment="written by hand"))
"""

from __future__ import annotations

import dataclasses
import enum
import re
import sys
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, TypeVar

from protocol.config_fields import (
    FieldError,
    checked,
    choices_text,
    field_must,
    file_fields,
    hints_of,
    union_args,
)
from protocol.errors import ConfigError

if sys.version_info >= (3, 11):  # noqa: UP036 - the Jetson's JetPack 6 has Python 3.10
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "dumps",
    "dumps_table",
    "load_toml",
    "parse_toml",
    "read_file",
    "read_table",
    "to_table",
]

T = TypeVar("T")
# the error a reader raises: ConfigError, or a format's own (a UserError and ValueError too)
ErrorType = Callable[[str], Exception]
_MISSING: Any = dataclasses.MISSING


def parse_toml(text: str, source: str, *, error: ErrorType = ConfigError) -> dict:
    """The table of TOML ``text``; ``error`` naming ``source`` when it is not valid TOML."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{source} is not valid TOML: {exc}") from None


def load_toml(
    path: Path | str, what: str, *, error: ErrorType = ConfigError
) -> tuple[dict[str, Any], str]:
    """(parsed table, raw text) of the TOML file ``path`` (``what`` it is, for errors)."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise error(f"{what} {p} does not exist; see docs/capture.md for an example") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read {what} {p}: {getattr(exc, 'strerror', None) or exc}") from None
    return parse_toml(text, str(p), error=error), text


def read_file(cls: type[T], path: Path | str, what: str, *, error: ErrorType = ConfigError) -> T:
    """The dataclass ``cls`` read from the TOML file ``path``."""
    table, _ = load_toml(path, what, error=error)
    return read_table(cls, table, str(path), error=error)


def read_table(
    cls: Any,
    table: object,
    where: str,
    *,
    base: Any = None,
    error: ErrorType = ConfigError,
) -> Any:
    """The dataclass ``cls`` (or, for a tagged union of dataclasses, the one its tag names) from a
    parsed TOML ``table``; ``where`` names the file (and table) in errors. With ``base``, keys
    left out keep ``base``'s values (a partial file that overrides a config)."""
    return _Reader(where, error).read(cls, table, "", base)


def _config_type(hint: Any) -> Any:
    """The dataclass (or the tuple of dataclasses of a tagged union) a field's type names."""
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return hint
    union = union_args(hint)
    if union is None:
        return None
    real = tuple(a for a in union if a is not type(None))
    if not all(isinstance(a, type) and dataclasses.is_dataclass(a) for a in real):
        return None
    return real[0] if len(real) == 1 else real


def _list_item_type(hint: Any) -> Any:
    """The dataclass (or tagged union) of a ``tuple[X, ...]`` field that holds tables."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple and len(args) == 2 and args[1] is Ellipsis:
        return _config_type(args[0])
    return None


class _Reader:
    """Reads one file's tables; ``where`` names the file (and the table the read began at),
    ``prefix`` is the dotted key of the table being read (``"ptp."``, ``"cameras[1]."``)."""

    def __init__(self, where: str, error: ErrorType) -> None:
        self.where, self.error = where, error

    def read(self, cls: Any, table: object, prefix: str, base: Any) -> Any:
        members = union_args(cls)
        if isinstance(cls, tuple) or members is not None:
            return self._tagged(tuple(members or cls), table, prefix)
        return self._dataclass(cls, table, prefix, base)

    def _at(self, prefix: str) -> str:
        return f"{self.where}: {prefix[:-1]}" if prefix else self.where

    def _dataclass(self, cls: Any, table: object, prefix: str, base: Any) -> Any:
        if not isinstance(table, dict):
            raise self.error(f"{self._at(prefix)}: expected a table of options, got {table!r}")
        fields = file_fields(cls)
        names = [f.name for f in fields]
        unknown = [prefix + k for k in table if k not in names]
        if unknown:
            what = f"[{prefix[:-1]}]" if prefix else "the table"
            raise self.error(
                f"{self.where}: unknown option {', '.join(map(repr, unknown))}; check the "
                f"spelling; {what} has: {', '.join(names)}"
            )
        hints = hints_of(cls)
        kw: dict[str, Any] = {}
        for f in fields:
            if f.name in table:
                current = getattr(base, f.name) if base is not None else None
                kw[f.name] = self._value(f, table[f.name], hints[f.name], prefix + f.name, current)
            elif base is None and f.default is _MISSING and f.default_factory is _MISSING:
                must = f"; {field_must(f)}" if field_must(f) else ""
                raise self.error(f"{self.where}: '{prefix}{f.name}' is required{must}")
        try:
            return dataclasses.replace(base, **kw) if base is not None else cls(**kw)
        except FieldError as exc:
            raise self.error(f"{self.where}: {prefix}{exc}") from None
        except (TypeError, ValueError) as exc:
            raise self.error(f"{self._at(prefix)}: {exc}") from None

    def _tagged(self, members: tuple[Any, ...], table: object, prefix: str) -> Any:
        if not isinstance(table, dict):
            raise self.error(f"{self._at(prefix)}: expected a table of options, got {table!r}")
        tag = next(
            name
            for name, hint in hints_of(members[0]).items()
            if typing.get_origin(hint) is Literal
            and all(typing.get_origin(hints_of(m).get(name)) is Literal for m in members)
        )
        kinds = {k: m for m in members for k in typing.get_args(hints_of(m)[tag])}
        if tag not in table:
            raise self.error(
                f"{self.where}: '{prefix}{tag}' is required: choose one of {choices_text(kinds)}"
            )
        kind = table[tag]
        if kind not in kinds:
            raise self.error(
                f"{self.where}: {prefix}{tag} = {kind!r}: choose one of {choices_text(kinds)}"
            )
        return self._dataclass(kinds[kind], table, prefix, None)

    def _value(self, f: dataclasses.Field, value: Any, hint: Any, name: str, current: Any) -> Any:
        nested = _config_type(hint)
        if nested is not None:
            keep = current if dataclasses.is_dataclass(current) else None
            value = self.read(nested, value, f"{name}.", keep)
        item = _list_item_type(hint)
        if item is not None:
            if not isinstance(value, list):
                raise self.error(f"{self.where}: {name} = {value!r}: must be a list of tables")
            value = tuple(self.read(item, v, f"{name}[{i}].", None) for i, v in enumerate(value))
        try:
            return checked(f, value, hint, name)
        except FieldError as exc:
            raise self.error(f"{self.where}: {exc}") from None


def to_table(obj: Any) -> dict[str, Any]:
    """The dataclass ``obj`` as a TOML table (what ``dumps`` writes)."""
    out: dict[str, Any] = {}
    for f in file_fields(type(obj)):
        value = getattr(obj, f.name)
        if value is not None:
            out[f.name] = _plain(value)
    return out


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_table(value)
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, Path):
        return str(value)
    return value


def dumps(obj: Any, *, comment: str = "", head: dict[str, Any] | None = None) -> str:
    """The dataclass ``obj`` as TOML text; ``comment`` lines go first (``# `` added), ``head``'s
    keys before the fields (a format version)."""
    return dumps_table({**(head or {}), **to_table(obj)}, comment=comment)


# tomli-w writes every array one item a line; an array of scalars is kept on one line, as people
# write them (and as the reconstructor's config.toml, whose text is hashed to resume a case, was
# always written).
_INLINE_ARRAY = re.compile(r"= \[\n((?:    [^\n\[\]{}]+,\n)+)\]")


def _inline(match: re.Match[str]) -> str:
    items = [line.strip().rstrip(",") for line in match.group(1).splitlines()]
    return "= [" + ", ".join(items) + "]"


def dumps_table(table: dict[str, Any], *, comment: str = "") -> str:
    """A table as TOML text (for a writer that cannot import the dataclass that reads it);
    enums, tuples and paths are written as their values, ``None`` left out."""
    import tomli_w  # writing is rarer than reading: the daemons never need it

    text = _INLINE_ARRAY.sub(_inline, tomli_w.dumps(_plain(table)))
    lines = "".join(f"# {line}\n" if line else "#\n" for line in comment.splitlines())
    return lines + text
