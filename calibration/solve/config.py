"""How the rig is solved: ``SolveConfig``, validated when made (``ConfigError`` names the field)."""

from __future__ import annotations

from dataclasses import dataclass

from protocol.errors import ConfigError

LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


@dataclass(frozen=True, kw_only=True)
class SolveConfig:
    """How to solve. The wand is rigid in the bundle adjustment (see ``calibration.solve.bundle``),
    so there is no weight between wand length and pixels: the spec's distances hold exactly."""

    loss: str = "soft_l1"
    loss_scale_px: float = 1.0
    cutoffs_px: tuple[float, ...] = (15.0, 5.0, 2.0, 1.0)
    cutoff_sigmas: float = 5.0  # never cut below this many robust SDs of the residuals
    max_sets: int = 1000  # bundle-adjust at most this many sets (see ``thin_sets``)
    max_nfev: int = 50  # solver evaluations per round
    reference_serial: int | None = None  # None: the camera that shares the most sets
    min_sets: int = 20  # sets a camera must share with some other camera
    min_pair_sets: int = 10  # sets two cameras must share to be linked in the linear start
    wand_tolerance: float = 0.05  # stereo-measured wand distances vs the spec, relative
    stereo_max_error_px: float = 2.0  # a camera's own triangulation must fit this well
    ransac_threshold_m: float = 0.03  # Kabsch inlier distance at 2 m (grows with depth²)
    ransac_iterations: int = 200
    seed: int = 0
    floor: bool = True  # look for the wand lying on the floor
    floor_min_still_s: float = 0.5
    floor_still_tolerance_px: float = 1.5  # "still": the wand's image moves less than this
    floor_max_height_m: float = 0.1
    floor_max_tilt_deg: float = 10.0
    pass_reprojection_px: float = 0.3  # verdict "pass" at or below this mean, and ...
    pass_wand_score: float = 0.5  # ... at or below this wand score, and ...
    pass_scale_tolerance: float = 0.005  # ... every camera's baseline agreeing with the wand

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ConfigError(f"SolveConfig.loss={self.loss!r}; choose one of {', '.join(LOSSES)}")
        positive = (
            *("loss_scale_px", "cutoff_sigmas", "wand_tolerance", "stereo_max_error_px"),
            *("ransac_threshold_m", "floor_still_tolerance_px", "floor_max_height_m"),
            *("floor_min_still_s", "floor_max_tilt_deg", "pass_reprojection_px"),
            *("pass_wand_score", "pass_scale_tolerance"),
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"SolveConfig.{name}={getattr(self, name)!r} must be > 0")
        cut = tuple(float(c) for c in self.cutoffs_px)
        if not cut or any(c <= 0 for c in cut) or list(cut) != sorted(cut, reverse=True):
            raise ConfigError(
                f"SolveConfig.cutoffs_px={self.cutoffs_px!r} must be positive and shrinking"
            )
        object.__setattr__(self, "cutoffs_px", cut)
        for name, low in (("max_sets", 20), ("max_nfev", 5), ("min_sets", 3)):
            if getattr(self, name) < low:
                raise ConfigError(f"SolveConfig.{name}={getattr(self, name)!r} must be >= {low}")
        if not 3 <= self.min_pair_sets <= self.min_sets:
            raise ConfigError(f"SolveConfig.min_pair_sets={self.min_pair_sets} must be 3..min_sets")
