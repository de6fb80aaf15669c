"""Finding a plug-in's factory by name: ``package.module:Class``, or an entry point of a group.

Stereo matchers (``egosurg.stereo_matchers``) and view refiners (``egosurg.refiners``) are
plug-ins the same way; each loader says what it calls the thing, which error to raise, and what
to use instead, and this finds the factory.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from collections.abc import Iterable
from typing import Any


def find_factory(
    name: str,
    *,
    group: str,
    what: str,
    error: type[Exception],
    known: Iterable[str],
    missing_hint: str,
) -> Any:
    """The object ``name`` names; ``error`` with a message naming ``what`` when there is none.

    ``missing_hint`` ends the message for an unknown name (what to install or use instead).
    """
    if ":" in name:
        module_name, _, attr = name.partition(":")
        try:
            return getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as exc:
            raise error(
                f"{what} {name!r} cannot be imported ({exc}); give 'package.module:Class' of an "
                f"installed module, or a name from the entry-point group {group!r}"
            ) from None
    eps = [ep for ep in importlib.metadata.entry_points(group=group) if ep.name == name]
    if not eps:
        raise error(f"no {what} called {name!r}: known are {', '.join(known)}. {missing_hint}")
    try:
        return eps[0].load()
    except Exception as exc:  # a broken plug-in: say which one, keep the cause
        raise error(
            f"{what} {name!r} (entry point {eps[0].value!r} in group {group!r}) failed to "
            f"import: {exc}; reinstall the plug-in"
        ) from exc
