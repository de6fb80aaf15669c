"""The one plug-in loader: stereo matchers and view refiners are found, checked and built here.

A plug-in is named either ``package.module:Class`` (for one not packaged yet) or by an entry
point of its group (``egosurg.stereo_matchers``, ``egosurg.refiners``). Each seam describes
itself once in a ``PluginKind`` (what it calls the thing, its base class, its errors, what to use
instead), and ``load_plugin`` does the rest the same way for both: find the factory, check the
local weights unless the factory says ``needs_weights = False``, call
``factory(weights_path=..., **options)`` and check that the result is an instance of the base.

Weights are never downloaded at run time (the machines that reconstruct cases may have no
internet): a plug-in that needs them gets a local path that ``check_weights`` has seen exist.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class PluginKind:
    """What one plug-in seam is called and how it fails."""

    group: str  # the entry-point group, e.g. "egosurg.refiners"
    what: str  # the thing's name in messages, e.g. "refiner"
    base: type  # a plug-in's factory must return an instance of this
    base_path: str  # where the base class is, for the "must subclass" message
    built_in: tuple[str, ...]  # names handled by the seam itself, listed first
    not_found: type[Exception]
    weights_error: type[Exception]
    fallback: str  # the built-in to use instead, e.g. "'guided', which needs none"

    def available(self) -> list[str]:
        """The built-in names, then every installed plug-in's."""
        names = {ep.name for ep in importlib.metadata.entry_points(group=self.group)}
        return [*self.built_in, *sorted(names - set(self.built_in))]


def find_factory(name: str, kind: PluginKind) -> Any:
    """The object ``name`` names; ``kind.not_found`` with a message naming it when there is none."""
    if ":" in name:
        module_name, _, attr = name.partition(":")
        try:
            return getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as exc:
            raise kind.not_found(
                f"{kind.what} {name!r} cannot be imported ({exc}); give 'package.module:Class' "
                f"of an installed module, or a name from the entry-point group {kind.group!r}"
            ) from None
    eps = [ep for ep in importlib.metadata.entry_points(group=kind.group) if ep.name == name]
    if not eps:
        raise kind.not_found(
            f"no {kind.what} called {name!r}: known are {', '.join(kind.available())}. "
            f"Another {kind.what} is a plug-in package that registers an entry point in the "
            f"group {kind.group!r}; install it (pip install <plug-in>) or use {kind.fallback}"
        )
    try:
        return eps[0].load()
    except Exception as exc:  # a broken plug-in: say which one, keep the cause
        raise kind.not_found(
            f"{kind.what} {name!r} (entry point {eps[0].value!r} in group {kind.group!r}) "
            f"failed to import: {exc}; reinstall the plug-in"
        ) from exc


def check_weights(
    name: str, weights_path: Path | None, kind: PluginKind, *, directory: bool = False
) -> Path:
    """``weights_path`` when it exists (a folder when ``directory``); else ``kind.weights_error``
    saying what to pass or what to use instead."""
    what = "weights directory" if directory else "weights path"
    if weights_path is None:
        raise kind.weights_error(
            f"{kind.what} {name!r} needs a local {what}: pass it (weights are never downloaded "
            "at run time; fetch them once from the model's authors on a machine with internet "
            f"and copy them here, see docs/refiners.md), or use {kind.fallback}"
        )
    path = Path(weights_path).expanduser()
    if not path.exists():
        raise kind.weights_error(
            f"{kind.what} {name!r}: {what} {path} does not exist; check the path"
        )
    if directory and not path.is_dir():
        raise kind.weights_error(
            f"{kind.what} {name!r}: {path} is a file, but a {what} in diffusers layout "
            "(vae/, unet/, scheduler/, ...) is needed; give the folder that holds them"
        )
    return path


def load_plugin(name: str, weights_path: Path | None, kind: PluginKind, **options: Any) -> Any:
    """The plug-in ``name`` of ``kind``, built as ``factory(weights_path=..., **options)``."""
    factory = find_factory(name, kind)
    if getattr(factory, "needs_weights", True):
        weights_path = check_weights(name, weights_path, kind)
    obj = factory(weights_path=None if weights_path is None else Path(weights_path), **options)
    if not isinstance(obj, kind.base):
        raise kind.not_found(
            f"{kind.what} {name!r} returned a {type(obj).__name__}, not a {kind.base.__name__}; "
            f"the plug-in must subclass {kind.base_path}"
        )
    log.info("%s %r loaded (weights %s)", kind.what, name, weights_path)
    return obj
