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


class TimestampError(ReconstructError):
    """A ``--at`` value that does not name a set of the session."""


class CalibrationMismatchError(ReconstructError):
    """A calibration that does not describe the session's cameras."""


class GpuUnavailableError(ReconstructError, RuntimeError):
    """The CUDA backend was asked for where it cannot run (no GPU, no CUDA torch, no gsplat)."""


class RefinerOutputError(ReconstructError, ValueError):
    """A refiner returned an image or mask of the wrong shape."""


class LpipsWeightsError(ReconstructError, FileNotFoundError):
    """A backbone weights file that is missing or is not AlexNet/VGG16 in torchvision's layout."""


class LpipsNotInstalledError(ReconstructError, ModuleNotFoundError):
    """The ``lpips`` package (for its linear heads) is not installed."""


class CaseFolderError(ReconstructError, ValueError):
    """A case folder that cannot be used: foreign, unwritable, another session or config."""


class CaseStorageError(CaseFolderError):
    """A stored model that is missing, damaged or of an unknown format."""


class CasePlanError(ReconstructError, ValueError):
    """A case range or interval the session cannot serve."""


class RayUnavailableError(ReconstructError, ConnectionError):
    """Ray is not installed, or its cluster does not answer."""


class TrajectoryTimeError(UserError, ValueError):
    """A time outside the trajectory's or the case's span."""


class CaseReplayError(ReconstructError, ValueError):
    """A case that cannot be replayed over the asked span; the message says what to do."""


class ObservedError(ReconstructError, ValueError):
    """A model whose input cameras cannot be found; the message says what to do."""


class SightlineError(ReconstructError, ValueError):
    """A line of sight that cannot be aimed (the eye inside the box) or a bad setting or offset."""


class SterileError(ReconstructError, ValueError):
    """A sterile field or its settings that cannot be checked; the message names which."""


class VideoOutputError(ReconstructError, OSError):
    """A replay video that cannot be written (no encoder, an unwritable path)."""


class ViewerError(ReconstructError, ValueError):
    """The viewer cannot start: the message says what to do."""
