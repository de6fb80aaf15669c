"""The reconstructor's errors: each one a ``UserError`` (the ``egosurg`` command prints it as one
line, no traceback) and the builtin it is most like, so callers can catch either.
"""

from __future__ import annotations

from protocol.errors import ConfigError, UserError


class ReconstructError(UserError):
    """Base of every reconstructor error a user can cause (bad input, bad environment)."""


class ReconstructConfigError(ReconstructError, ConfigError):
    """A reconstructor option with a value that cannot work; the message names field and value."""


class StereoError(ReconstructError, ValueError):
    """A stereo pair or its calibration that cannot be matched (sizes, uncalibrated pose, ...)."""


class MatcherNotFoundError(ReconstructError, LookupError):
    """No stereo matcher plug-in of the requested name is installed."""


class MatcherWeightsError(ReconstructError, FileNotFoundError):
    """A learned stereo matcher was asked for without a usable weights file."""


class FusionError(ReconstructError, ValueError):
    """Point clouds that cannot be fused (wrong shapes, nothing left to fuse)."""


class SplatFormatError(ReconstructError, ValueError):
    """A file that is not a Gaussian splat PLY (or ``.splat``) this reader understands."""


class RefinerNotFoundError(ReconstructError, LookupError):
    """No view refiner of the requested name is built in or installed as a plug-in."""


class RefinerWeightsError(ReconstructError, FileNotFoundError):
    """A learned view refiner was asked for without a usable local weights directory."""


class DepthCacheError(ReconstructError, OSError):
    """A depth cache folder that cannot be used (a file, not writable)."""
