"""How to match one stereo pair: ``StereoConfig``, shared by the rectifier and the SGBM matcher.

It lives apart from ``stereo.py`` so that the matchers (``sgbm.py``) and the depth code
(``stereo.py``) both import it, and neither imports the other's caller.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from reconstructor.errors import ReconstructConfigError


@dataclass(frozen=True, kw_only=True)
class StereoConfig:
    """How to match one pair. ``for_resolution`` gives the defaults for a ZED X mode."""

    min_depth_m: float = 0.4  # the cameras hang above head height: nothing nearer matters
    max_depth_m: float = 8.0
    # Match on the rectified pair resized by this factor; 0: by the image's width
    # (``scale_for``: 0.5 above 1280 px, so HD1200/HD1080 match at half size, else 1.0), so a
    # config that sets other stereo keys keeps the resolution's default.
    match_scale: float = 0.0
    block_size_px: int = 5
    uniqueness_ratio: int = 10
    speckle_window_px: int = 100
    speckle_range_px: int = 2
    wls_lambda: float = 8000.0
    wls_sigma_color: float = 1.5
    lr_max_diff_px: float = 1.0
    # Retuned on the sim's true depth (EVALUATION.md "Stereo depth against the sim's
    # truth"): ZNCC 0.3 instead of 0.5 answers on 84 % of textured pixels instead of 74 % (the
    # right edge as dense as the centre there) for 12.5 % of depths > 3 % off instead of 10.6 %.
    # The WLS agreement of 1.0 px as well (92 %, 18 %) was measured and not adopted: with both,
    # the arm that reaches over the drape in tests/reconstructor/test_sterile.py's short case
    # was lost, with either alone it was found.
    wls_max_change_px: float = 0.5
    # Where the WLS map and SGBM's own disparity differ by more than wls_max_change_px but at
    # most this, keep SGBM's (0: drop every such pixel, as the paper's tables were measured).
    # 1.5 with zncc_warp_failed_by_best (bench/configs/stereo_dense.toml): real pairs 80 % dense
    # instead of 64 % at <= 2.9 % bad answers, but on the sim 19 % of depths > 3 % off instead of
    # 12.5 % (EVALUATION.md, "Stereo depth on real images"). Off until the protocols are rerun.
    keep_sgbm_within_px: float = 0.0
    # Beyond keep_sgbm_within_px and up to this, keep SGBM's own disparity only where it is
    # smooth around the pixel (it varies by at most 1 px over its 5 x 5 neighbours: not at a
    # depth edge, where SGBM's blocks fatten). 0: off. 2.5 with keep_sgbm_within_px 1.5: on real
    # pairs 1.1 points denser (Motorcycle's bad answers 2.94 -> 3.06 %), on the sim 0.5-0.6
    # points more depths > 3 % off; with fill_left_border as well (bench/configs/
    # stereo_densest.toml) 84.9 % dense at <= 2.98 % bad (EVALUATION.md, "Towards 85 %").
    keep_smooth_sgbm_within_px: float = 0.0
    min_zncc: float = 0.3
    zncc_window_px: int = 7
    # How the photometric check warps the neighbours in a pixel's window that failed the
    # left-right or WLS check: False warps them by 0 (the paper's tables were measured so);
    # True by their best estimate (SGBM's, else WLS's), so a confident pixel is not dropped for
    # its neighbours: 5-7 points denser on real pairs at the same share of bad answers, but on the
    # sim 2 points more depths > 3 % off (EVALUATION.md, "Stereo depth on real images"). Off until
    # the near-field and egocentric protocols are rerun with it.
    zncc_warp_failed_by_best: bool = False
    # Fill each row's leading hole, the left border's band whose partner lies outside the right
    # image, with the row's first answer, where the hole is no wider than that answer's
    # disparity plus ``left_border_slack_px`` (``stereo_occlusion.py``). On real pairs with
    # bench/configs/stereo_dense.toml's options 2.7-4.1 points denser, 0.4-22 % of the filled
    # pixels > 2 px off; on the sim 0.4-0.5 points more depths > 3 % off (EVALUATION.md,
    # "Towards 85 %"). Off by default for that.
    fill_left_border: bool = False
    left_border_slack_px: float = 8.0
    rectify_alpha: float = 0.0  # 0: crop to pixels every sensor saw; 1: keep every sensor pixel

    def __post_init__(self) -> None:
        def bad(field: str, value: object, why: str) -> ReconstructConfigError:
            return ReconstructConfigError(f"StereoConfig.{field}={value!r}: {why}")

        if not 0 < self.min_depth_m < self.max_depth_m:
            raise bad(
                "min_depth_m",
                self.min_depth_m,
                f"must be positive and below max_depth_m={self.max_depth_m!r}",
            )
        if self.match_scale != 0 and not 0.1 <= self.match_scale <= 1.0:
            raise bad("match_scale", self.match_scale, "must be in [0.1, 1], or 0 (by width)")
        if self.block_size_px < 1 or self.block_size_px % 2 == 0 or self.block_size_px > 11:
            raise bad("block_size_px", self.block_size_px, "must be odd, from 1 to 11")
        if not 0 <= self.uniqueness_ratio <= 100:
            raise bad("uniqueness_ratio", self.uniqueness_ratio, "must be a percentage 0-100")
        if self.speckle_window_px < 0 or self.speckle_range_px < 0:
            raise bad("speckle_window_px", self.speckle_window_px, "speckle settings must be >= 0")
        if self.wls_lambda <= 0 or self.wls_sigma_color <= 0:
            raise bad("wls_lambda", self.wls_lambda, "WLS lambda and sigma must be positive")
        if self.lr_max_diff_px <= 0:
            raise bad("lr_max_diff_px", self.lr_max_diff_px, "must be positive")
        if self.wls_max_change_px <= 0:
            raise bad("wls_max_change_px", self.wls_max_change_px, "must be positive")
        if self.keep_sgbm_within_px < 0:
            raise bad("keep_sgbm_within_px", self.keep_sgbm_within_px, "must be >= 0 (0: off)")
        if self.keep_smooth_sgbm_within_px < 0:
            raise bad(
                "keep_smooth_sgbm_within_px",
                self.keep_smooth_sgbm_within_px,
                "must be >= 0 (0: off)",
            )
        if self.left_border_slack_px < 0:
            raise bad("left_border_slack_px", self.left_border_slack_px, "must be >= 0")
        if not -1.0 <= self.min_zncc < 1.0:
            raise bad("min_zncc", self.min_zncc, "must be in [-1, 1) (-1 disables the check)")
        if self.zncc_window_px < 3 or self.zncc_window_px % 2 == 0:
            raise bad("zncc_window_px", self.zncc_window_px, "must be odd and at least 3")
        if not 0.0 <= self.rectify_alpha <= 1.0:
            raise bad("rectify_alpha", self.rectify_alpha, "must be in [0, 1]")

    @classmethod
    def for_resolution(cls, width_px: int, **overrides: object) -> StereoConfig:
        """Defaults for an image ``width_px`` wide: HD1200/HD1080 (1920) match at half size.

        Measured on the sim at HD1200: half size takes ~0.9 s per pair with a median error of
        0.8-0.9 % at 1-4 m; full size (``match_scale=1.0``) halves the error (0.4-0.5 %) but
        takes ~5-6 s and covers fewer pixels, worth it only when time does not matter."""
        return cls(**overrides).for_width(width_px)  # type: ignore[arg-type]

    def scale_for(self, width_px: int) -> float:
        """The match scale for an image ``width_px`` wide: ``match_scale``, or where that is 0
        the resolution's default (half size above 1280 px)."""
        if self.match_scale:
            return self.match_scale
        return 0.5 if width_px > 1280 else 1.0

    def for_width(self, width_px: int) -> StereoConfig:
        """This config with its match scale fixed for an image ``width_px`` wide."""
        return replace(self, match_scale=self.scale_for(width_px))
