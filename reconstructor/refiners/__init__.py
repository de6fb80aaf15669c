"""View refiners for the auxiliary views, and ``load_refiner``, which picks one by name.

Names:
- ``"guided"``: reference-guided correction, no weights (``guided.py``; ``config`` is a
  ``GuidedConfig`` or None for the defaults);
- ``"difix"``: the Difix3D adapter (``difix.py``), needs the optional extra
  ``pip install 'egosurg[difix]'`` and a local weights directory in diffusers layout
  (``config``: a ``DifixConfig`` or None);
- ``"none"``: the render unchanged (``IdentityRefiner``);
- a plug-in registered in the entry-point group ``egosurg.refiners``::

      [project.entry-points."egosurg.refiners"]
      my_refiner = "my_plugin.refiner:MyRefiner"

- or ``"package.module:Class"`` for one not packaged yet.

A plug-in factory is called as ``factory(weights_path=..., config=...)`` and must return a
``Refiner``; unless it sets ``needs_weights = False`` the weights path must exist. Example::

    refiner = load_refiner("difix", Path("~/weights/difix_ref").expanduser())
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
from pathlib import Path
from typing import Any

from reconstructor.errors import RefinerNotFoundError, RefinerWeightsError
from reconstructor.plugins import find_factory
from reconstructor.refiners.base import IdentityRefiner, Refined, Refiner, RefineRequest
from reconstructor.refiners.guided import GuidedConfig, GuidedRefiner

__all__ = [
    "ENTRY_POINT_GROUP",
    "GuidedConfig",
    "GuidedRefiner",
    "IdentityRefiner",
    "RefineRequest",
    "Refined",
    "Refiner",
    "available_refiners",
    "load_refiner",
]

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "egosurg.refiners"
BUILT_IN = ("guided", "difix", "none")
DIFIX_EXTRA_HINT = "pip install 'egosurg[difix]'"


def available_refiners() -> list[str]:
    """Names ``load_refiner`` accepts: the built-in ones and every installed plug-in."""
    names = {ep.name for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    return [*BUILT_IN, *sorted(names - set(BUILT_IN))]


def load_refiner(
    name: str, weights: Path | None = None, *, config: object | None = None
) -> Refiner:
    """The refiner called ``name`` (module docstring), with its local ``weights`` if it needs them.

    Raises ``RefinerNotFoundError`` for an unknown name or a missing optional extra, and
    ``RefinerWeightsError`` for missing or unusable weights.
    """
    weights_path = None if weights is None else Path(weights).expanduser()
    if name == "guided":
        return GuidedRefiner(config)  # type: ignore[arg-type]  # it checks the type itself
    if name == "none":
        return IdentityRefiner()
    if name == "difix":
        return _load_difix(weights_path, config)
    factory = _find_factory(name)
    if getattr(factory, "needs_weights", True):
        _check_weights(name, weights_path)
    refiner = factory(weights_path=weights_path, config=config)
    if not isinstance(refiner, Refiner):
        raise RefinerNotFoundError(
            f"refiner {name!r} returned a {type(refiner).__name__}, not a Refiner; the plug-in "
            "must subclass reconstructor.refiners.Refiner"
        )
    log.info("refiner %r loaded (weights %s)", name, weights_path)
    return refiner


def _load_difix(weights_path: Path | None, config: object | None) -> Refiner:
    _check_weights("difix", weights_path, directory=True)
    try:
        import diffusers  # noqa: F401  # the optional extra: only this branch needs it
        import transformers  # noqa: F401
    except ImportError as exc:
        raise RefinerNotFoundError(
            f"the 'difix' refiner needs the optional extra ({exc}); install it with "
            f"{DIFIX_EXTRA_HINT}, or use the 'guided' refiner"
        ) from None
    from reconstructor.refiners.difix import DifixRefiner

    assert weights_path is not None  # checked above
    return DifixRefiner(weights_path, config)  # type: ignore[arg-type]  # it checks the type


def _find_factory(name: str) -> Any:
    return find_factory(
        name,
        group=ENTRY_POINT_GROUP,
        what="refiner",
        error=RefinerNotFoundError,
        known=available_refiners(),
        missing_hint=(
            f"Another refiner is a plug-in package that registers an entry point in the group "
            f"{ENTRY_POINT_GROUP!r}; install it (pip install <plug-in>) or use 'guided'"
        ),
    )


def _check_weights(name: str, weights_path: Path | None, *, directory: bool = False) -> None:
    what = "weights directory" if directory else "weights path"
    if weights_path is None:
        raise RefinerWeightsError(
            f"refiner {name!r} needs a local {what}: pass it (weights are never downloaded at run "
            "time; fetch them once on a machine with internet and copy them here, see "
            "docs/refiners.md), or use the 'guided' refiner, which needs none"
        )
    if not weights_path.exists():
        raise RefinerWeightsError(
            f"refiner {name!r}: {what} {weights_path} does not exist; check the path"
        )
    if directory and not weights_path.is_dir():
        raise RefinerWeightsError(
            f"refiner {name!r}: {weights_path} is a file, but a {what} in diffusers layout "
            "(vae/, unet/, scheduler/, ...) is needed; give the folder that holds them"
        )
