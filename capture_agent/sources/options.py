"""Typed reading of one TOML table, with errors that name the file, the field and the bad value.

Each backend's config dataclass reads its table through a ``TableReader`` (types, unknown keys) and
checks ranges and choices in its own ``__post_init__`` (so a config built in code is checked the
same way); ``from_table`` prefixes those messages with ``where`` (the file and table).

Example::

    r = TableReader({"fps": 30, "resolution": "SVGA"}, "node.toml [[cameras]] #1")
    fps = r.number("fps", 30.0)
    r.finish()   # ConfigError if the table has keys nobody asked for (typos)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from protocol.errors import ConfigError

REQUIRED: Any = object()

# Keys that the node config uses to pick the backend; a backend ignores them.
SELECTOR_KEYS = ("source", "kind")


def require(ok: bool, field: str, value: object, must: str) -> None:
    """Raise ``ConfigError("<field> = <value>: <must>")`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{field} = {value!r}: {must}")


class TableReader:
    def __init__(
        self, table: dict[str, Any], where: str, *, ignore: Sequence[str] = SELECTOR_KEYS
    ) -> None:
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: expected a table of options, got {type(table).__name__}")
        self.table = table
        self.where = where
        self._ignore = set(ignore)
        self._used: set[str] = set(ignore)

    def _get(self, key: str, default: Any, hint: str) -> tuple[bool, Any]:
        self._used.add(key)
        if key in self.table:
            return True, self.table[key]
        if default is REQUIRED:
            raise ConfigError(f"{self.where}: '{key}' is required; {hint}")
        return False, default

    def _bad(self, key: str, value: object, must: str) -> ConfigError:
        return ConfigError(f"{self.where}: {key} = {value!r}: {must}")

    def integer(self, key: str, default: Any = REQUIRED, *, hint: str = "an integer") -> Any:
        present, value = self._get(key, default, hint)
        if present and (isinstance(value, bool) or not isinstance(value, int)):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def number(self, key: str, default: Any = REQUIRED, *, hint: str = "a number") -> Any:
        present, value = self._get(key, default, hint)
        if not present:
            return value
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self._bad(key, value, f"must be {hint}")
        return float(value)

    def boolean(self, key: str, default: Any = REQUIRED) -> Any:
        present, value = self._get(key, default, "true or false")
        if present and not isinstance(value, bool):
            raise self._bad(key, value, "must be true or false (TOML booleans are unquoted)")
        return value

    def text(self, key: str, default: Any = REQUIRED, *, hint: str = "a string") -> Any:
        present, value = self._get(key, default, hint)
        if present and not isinstance(value, str):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def choice(self, key: str, choices: Sequence[str], default: Any = REQUIRED) -> Any:
        valid = ", ".join(repr(c) for c in choices)
        present, value = self._get(key, default, f"choose one of {valid}")
        if present and value not in choices:
            raise self._bad(key, value, f"choose one of {valid}")
        return value

    def tables(self, key: str, *, hint: str = "a list of tables") -> list[dict[str, Any]]:
        present, value = self._get(key, [], hint)
        if not present:
            return []
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def finish(self) -> None:
        """Reject keys that were never read: a typo must not silently fall back to a default."""
        unknown = sorted(set(self.table) - self._used)
        if unknown:
            known = ", ".join(sorted(self._used - self._ignore))
            raise ConfigError(
                f"{self.where}: unknown option(s) {', '.join(unknown)}; "
                f"the valid options are {known}"
            )
