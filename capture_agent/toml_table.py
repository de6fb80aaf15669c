"""The one way capture_agent reads TOML: a file with clear errors, and typed reading of one table
whose errors name the file, the table, the field and the bad value.

node.toml and rig.toml (``capture_agent/config.py``), their ``[security]`` tables, the ``[ptp]``
table and every camera source's ``[[cameras]]`` table read their fields through a
``TableReader``. A config dataclass checks ranges and choices either here (``check=``, for the
node and rig tables) or in its own ``__post_init__`` through ``require`` (so a config built in
code is checked the same way); ``from_table`` prefixes those messages with ``where``.

Example::

    r = TableReader({"fps": 30, "resolution": "SVGA"}, "node.toml [[cameras]] #1")
    fps = r.number("fps", 30.0, check=lambda v: 1 <= v <= 120, hint="a number from 1 to 120")
    r.finish()   # ConfigError if the table has keys nobody asked for (typos)
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from protocol.errors import ConfigError

REQUIRED: Any = object()


def load_toml(path: Path | str, what: str) -> tuple[dict[str, Any], str]:
    """(parsed table, raw text) of a TOML file, with clear errors."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise ConfigError(
            f"{what} {p} does not exist; see docs/capture.md for an example"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {p}: {exc.strerror}") from None
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p} is not valid TOML: {exc}") from None


def require(ok: bool, field: str, value: object, must: str) -> None:
    """Raise ``ConfigError("<field> = <value>: <must>")`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{field} = {value!r}: {must}")


class TableReader:
    """Typed access to one TOML table. ``hint`` says what a value must be ("an integer from 1 to
    100"); it completes every message about that field. ``ignore`` lists keys that belong to
    someone else (a camera table's ``source``, which picks the backend)."""

    def __init__(self, table: object, where: str, *, ignore: Sequence[str] = ()) -> None:
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: expected a table of options, got {type(table).__name__}")
        self.table: dict[str, Any] = table
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

    def _checked(self, key: str, value: Any, check: Callable[[Any], Any] | None, hint: str) -> Any:
        if check is not None and not check(value):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def integer(
        self,
        key: str,
        default: Any = REQUIRED,
        *,
        hint: str = "an integer",
        check: Callable[[int], Any] | None = None,
    ) -> Any:
        present, value = self._get(key, default, hint)
        if not present:
            return value
        if isinstance(value, bool) or not isinstance(value, int):
            raise self._bad(key, value, f"must be {hint}")
        return self._checked(key, value, check, hint)

    def number(
        self,
        key: str,
        default: Any = REQUIRED,
        *,
        hint: str = "a number",
        check: Callable[[float], Any] | None = None,
    ) -> Any:
        present, value = self._get(key, default, hint)
        if not present:
            return value
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self._bad(key, value, f"must be {hint}")
        return self._checked(key, float(value), check, hint)

    def boolean(self, key: str, default: Any = REQUIRED) -> Any:
        present, value = self._get(key, default, "true or false")
        if present and not isinstance(value, bool):
            raise self._bad(key, value, "must be true or false (TOML booleans are unquoted)")
        return value

    def text(
        self,
        key: str,
        default: Any = REQUIRED,
        *,
        hint: str = "a string",
        check: Callable[[str], Any] | None = None,
    ) -> Any:
        present, value = self._get(key, default, hint)
        if not present:
            return value
        if not isinstance(value, str):
            raise self._bad(key, value, f"must be {hint}")
        return self._checked(key, value, check, hint)

    def choice(self, key: str, choices: Sequence[str], default: Any = REQUIRED) -> Any:
        valid = ", ".join(repr(c) for c in choices)
        present, value = self._get(key, default, f"choose one of {valid}")
        if present and value not in choices:
            raise self._bad(key, value, f"choose one of {valid}")
        return value

    def texts(self, key: str, default: Any = REQUIRED, *, hint: str = "a list of strings") -> Any:
        present, value = self._get(key, default, hint)
        if present and (
            not isinstance(value, list) or not all(isinstance(v, str) and v for v in value)
        ):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def integers(
        self, key: str, default: Any = REQUIRED, *, hint: str = "a list of integers"
    ) -> Any:
        """A list of positive integers (camera serial numbers)."""
        present, value = self._get(key, default, hint)
        if present and (
            not isinstance(value, list)
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
        ):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def tables(self, key: str, *, hint: str = "a list of tables") -> list[dict[str, Any]]:
        present, value = self._get(key, [], hint)
        if not present:
            return []
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise self._bad(key, value, f"must be {hint}")
        return value

    def table_of(self, key: str) -> dict[str, Any]:
        """A sub-table such as ``[ptp]`` (empty when absent), read by its own reader later."""
        present, value = self._get(key, {}, "a table")
        if present and not isinstance(value, dict):
            raise ConfigError(f"{self.where}: [{key}] must be a table")
        return value

    def skip(self, *keys: str) -> None:
        """Keys another reader checks (a sub-table, a list of tables): not unknown here."""
        self._used.update(keys)

    def finish(self) -> None:
        """Reject keys that were never read: a typo must not silently fall back to a default."""
        unknown = sorted(set(self.table) - self._used)
        if unknown:
            known = ", ".join(sorted(self._used - self._ignore))
            raise ConfigError(
                f"{self.where}: unknown option(s) {', '.join(unknown)}; check the spelling; "
                f"the valid options are {known}"
            )
