"""Picking a stereo matcher by name: the built-in SGBM matcher or a plug-in.

The default matcher is OpenCV SGBM with a WLS filter (``"sgbm"``, ``SgbmWlsMatcher``). A
learned matcher such as FoundationStereo, whose weights come from outside any package registry,
is a plug-in: a package registers a factory in the entry-point group ``egosurg.stereo_matchers``::

    [project.entry-points."egosurg.stereo_matchers"]
    foundation_stereo = "my_plugin.matcher:FoundationStereoMatcher"

and the user names it with a local weights file::

    matcher = load_matcher("foundation_stereo", Path("~/weights/foundation_stereo.pth"))

The factory is called as ``factory(weights_path=...)`` and must return a ``StereoMatcher``. A
``"package.module:Class"`` string works the same way without an entry point (for trying a matcher
before packaging it).
"""

from __future__ import annotations

from pathlib import Path

from reconstructor.depth.matcher import StereoMatcher
from reconstructor.depth.sgbm import SgbmWlsMatcher
from reconstructor.depth.stereo_config import StereoConfig
from reconstructor.errors import MatcherNotFoundError, MatcherWeightsError
from reconstructor.plugins import PluginKind, load_plugin

ENTRY_POINT_GROUP = "egosurg.stereo_matchers"
MATCHERS = PluginKind(
    group=ENTRY_POINT_GROUP,
    what="stereo matcher",
    base=StereoMatcher,
    base_path="reconstructor.depth.matcher.StereoMatcher",
    built_in=("sgbm",),
    not_found=MatcherNotFoundError,
    weights_error=MatcherWeightsError,
    fallback="the built-in 'sgbm' matcher, which needs none",
)


def available_matchers() -> list[str]:
    """Names ``load_matcher`` accepts: ``"sgbm"`` and every installed plug-in."""
    return MATCHERS.available()


def load_matcher(
    name: str, weights_path: Path | None = None, *, config: StereoConfig | None = None
) -> StereoMatcher:
    """The matcher called ``name``: ``"sgbm"``, an installed plug-in, or ``"module:Class"``.

    ``config`` tunes the SGBM default and is ignored by plug-ins.
    """
    if name == "sgbm":
        return SgbmWlsMatcher(config)
    matcher: StereoMatcher = load_plugin(name, weights_path, MATCHERS)
    return matcher
