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

from pathlib import Path

from reconstructor.errors import RefinerNotFoundError, RefinerWeightsError
from reconstructor.plugins import PluginKind, check_weights, load_plugin
from reconstructor.refine.base import IdentityRefiner, Refiner
from reconstructor.refine.guided import GuidedRefiner

ENTRY_POINT_GROUP = "egosurg.refiners"
DIFIX_EXTRA_HINT = "pip install 'egosurg[difix]'"
REFINERS = PluginKind(
    group=ENTRY_POINT_GROUP,
    what="refiner",
    base=Refiner,
    base_path="reconstructor.refine.base.Refiner",
    built_in=("guided", "difix", "none"),
    not_found=RefinerNotFoundError,
    weights_error=RefinerWeightsError,
    fallback="the 'guided' refiner, which needs none",
)


def available_refiners() -> list[str]:
    """Names ``load_refiner`` accepts: the built-in ones and every installed plug-in."""
    return REFINERS.available()


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
    refiner: Refiner = load_plugin(name, weights_path, REFINERS, config=config)
    return refiner


def _load_difix(weights_path: Path | None, config: object | None) -> Refiner:
    folder = check_weights("difix", weights_path, REFINERS, directory=True)
    try:
        import diffusers  # noqa: F401  # the optional extra: only this branch needs it
        import transformers  # noqa: F401
    except ImportError as exc:
        raise RefinerNotFoundError(
            f"the 'difix' refiner needs the optional extra ({exc}); install it with "
            f"{DIFIX_EXTRA_HINT}, or use the 'guided' refiner"
        ) from None
    from reconstructor.refine.difix import DifixRefiner

    return DifixRefiner(folder, config)  # type: ignore[arg-type]  # it checks the type
