"""Metric depth from one calibrated stereo pair: rectify, match, triangulate.

Steps (all on the CPU):
1. rectify both distorted sensor images with ``cv2.stereoRectify`` (``CALIB_ZERO_DISPARITY``, so
   disparity is simply ``x_left - x_right``) and cached ``initUndistortRectifyMap`` maps; for
   HD1200, shrink the rectified pair by ``match_scale`` (area averaging) before matching;
2. match with a ``StereoMatcher`` (``matcher.py``; picked by name in ``matchers.py``). The
   default is SGBM (``MODE_SGBM_3WAY``, P1 = 8·c·w², P2 = 32·c·w², 1/16-pixel disparities)
   with a right-view matcher and a WLS filter (λ ≈ 8000, σ ≈ 1.5); a pixel keeps its
   WLS-filtered disparity only where a left-right check, a patch correlation check and a WLS
   agreement check all pass (``sgbm.SgbmWlsMatcher`` says why each is there). A learned
   matcher plugs in at the same seam;
3. ``depth = f · B / d`` in the rectified left camera, kept inside ``[min_depth_m, max_depth_m]``
   and where both images' pixels came from inside the sensors.

The search range comes from the depth range: ``d = f · B / depth`` with the rectified focal
length at match resolution and the calibrated baseline.

Measured on the simulator (SVGA, noisy sensor images through JPEG 90, 4 cameras, every phase;
``bench/bench_stereo.py``, EVALUATION.md): 83-85 % of textured surfaces and ~11 % of blank walls
and ceiling get a depth, 12-13 % of valid depths are more than 3 % off and 5-6 % more than 5 %
(most of those on the blank surfaces); about 0.5 s per pair on 2 cores (HD1200 at
``match_scale`` 0.5: about 1.2 s). On real pairs with ground truth (Middlebury Motorcycle and
Aloe, ``bench/bench_stereo_real.py``) it answers on 62-69 % of the pixels, with 0.3-2.3 % of its
answers more than 2 px off (OpenCV's textbook SGBM+WLS: 78-89 %, 9-13 %); with the two options of
``bench/configs/stereo_dense.toml`` (``zncc_warp_failed_by_best``, ``keep_sgbm_within_px``) on
77-84 % with 0.6-2.9 % bad, for 19-20 % of the sim's depths more than 3 % off instead of 12-13 %;
with ``keep_smooth_sgbm_within_px`` and ``fill_left_border`` as well
(``bench/configs/stereo_densest.toml``) on 82-88 % with 1.2-3.0 % bad.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.camera import Intrinsics, Pose
from reconstructor.depth.matcher import StereoMatcher
from reconstructor.depth.sgbm import SgbmWlsMatcher
from reconstructor.depth.stereo_config import StereoConfig
from reconstructor.errors import StereoError

log = logging.getLogger(__name__)

MIN_BASELINE_M = 0.01  # below this a pair is uncalibrated (an identity pose), not a stereo rig
MAX_RELATIVE_ROTATION_DEG = 15.0


class StereoRectifier:
    """Rectification of one sensor pair, with its maps built once.

    ``rect_from_left`` / ``rect_from_right`` rotate each sensor's camera frame into the common
    rectified frame; ``intrinsics`` is the rectified left pinhole at match resolution.
    """

    def __init__(
        self,
        left: Intrinsics,
        right: Intrinsics,
        right_from_left: Pose,
        *,
        match_scale: float = 1.0,
        alpha: float = 0.0,
    ) -> None:
        check_stereo_calibration(left, right, right_from_left)
        size = (left.width_px, left.height_px)
        R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
            left.K,
            left.dist_array,
            right.K,
            right.dist_array,
            size,
            right_from_left.R,
            right_from_left.t_m.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=alpha,
        )
        self.rect_from_left: np.ndarray = R1
        self.rect_from_right: np.ndarray = R2
        self.P_left: np.ndarray = P1  # full resolution
        self.P_right: np.ndarray = P2
        self.baseline_m = float(-P2[0, 3] / P2[0, 0])
        self.full_size = size
        self.match_size = (round(size[0] * match_scale), round(size[1] * match_scale))
        self.map_left = cv2.initUndistortRectifyMap(
            left.K, left.dist_array, R1, P1[:, :3], size, cv2.CV_32FC1
        )
        self.map_right = cv2.initUndistortRectifyMap(
            right.K, right.dist_array, R2, P2[:, :3], size, cv2.CV_32FC1
        )
        sx = self.match_size[0] / size[0]
        sy = self.match_size[1] / size[1]
        # area resize: match pixel i covers full pixels [i/s, (i+1)/s), centre (i + 0.5)/s - 0.5
        self.intrinsics = Intrinsics(
            width_px=self.match_size[0],
            height_px=self.match_size[1],
            fx_px=float(P1[0, 0] * sx),
            fy_px=float(P1[1, 1] * sy),
            cx_px=float((P1[0, 2] + 0.5) * sx - 0.5),
            cy_px=float((P1[1, 2] + 0.5) * sy - 0.5),
        )
        self._inside = (self._inside_mask(self.map_left), self._inside_mask(self.map_right))

    def _inside_mask(self, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Match-resolution pixels whose whole footprint came from inside the sensor."""
        w, h = self.full_size
        mx, my = maps
        inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        if self.match_size == self.full_size:
            return inside
        small = cv2.resize(
            inside.astype(np.uint8) * 255, self.match_size, interpolation=cv2.INTER_AREA
        )
        return small == 255

    def rectify(
        self, left_rgb: np.ndarray, right_rgb: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Both images rectified at match resolution, and each one's inside-the-sensor mask."""
        out = []
        for img, (mx, my) in ((left_rgb, self.map_left), (right_rgb, self.map_right)):
            rect = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            if self.match_size != self.full_size:
                rect = cv2.resize(rect, self.match_size, interpolation=cv2.INTER_AREA)
            out.append(rect)
        return out[0], out[1], self._inside[0], self._inside[1]


def check_stereo_calibration(left: Intrinsics, right: Intrinsics, right_from_left: Pose) -> None:
    """Refuse a pair that is not a calibrated, side-by-side stereo rig, saying what is wrong."""
    if (left.width_px, left.height_px) != (right.width_px, right.height_px):
        raise StereoError(
            f"left intrinsics are for {left.width_px}x{left.height_px} but right intrinsics are "
            f"for {right.width_px}x{right.height_px}; use both sensors' calibration at one "
            "resolution"
        )
    t_mm = right_from_left.t_m * 1000.0
    baseline_m = float(np.linalg.norm(right_from_left.t_m))
    if baseline_m < MIN_BASELINE_M:
        raise StereoError(
            f"right_from_left has a baseline of {baseline_m * 1000:.1f} mm: the stereo pair is "
            "uncalibrated (an identity pose?). Use the camera's factory calibration "
            "(SN<serial>.conf via protocol.formats.zed_conf) or the rig calibration's "
            "left-to-right pose"
        )
    if t_mm[0] >= 0 or abs(t_mm[0]) < 0.8 * np.linalg.norm(t_mm):
        raise StereoError(
            f"right_from_left puts the right sensor at T = {np.round(t_mm, 1).tolist()} mm from "
            "the left; a ZED X pair has T close to [-120, 0, 0] mm (x_right = R x_left + T). "
            "Are the left and right images or sensors swapped?"
        )
    angle_deg = math.degrees(
        math.acos(float(np.clip((np.trace(right_from_left.R) - 1) / 2, -1.0, 1.0)))
    )
    if angle_deg > MAX_RELATIVE_ROTATION_DEG:
        raise StereoError(
            f"right_from_left rotates by {angle_deg:.1f} degrees; a stereo rig's sensors are "
            f"nearly parallel (< {MAX_RELATIVE_ROTATION_DEG:.0f} degrees). Check the calibration"
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class DepthMap:
    """Depth of one stereo pair, in the rectified left camera at match resolution.

    ``depth_m`` (H, W) float32 is z in the rectified left frame, NaN where ``valid`` is False;
    ``disparity_px`` (H, W) float32 is the matcher's output (NaN where it had no match);
    ``intrinsics`` is that frame's pinhole (no distortion); ``rect_from_left`` (3, 3) rotates the
    original left sensor frame into it (``x_rect = R @ x_left``); ``baseline_m`` is the
    calibrated baseline; ``rgb`` (H, W, 3) uint8 is the rectified left image.
    """

    depth_m: np.ndarray
    valid: np.ndarray
    disparity_px: np.ndarray
    intrinsics: Intrinsics
    rect_from_left: np.ndarray
    baseline_m: float
    rgb: np.ndarray

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())

    def points_in_left_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """Valid pixels as ((M, 3) float32 points in the ORIGINAL left sensor frame, metres;
        (M, 3) float32 colours in 0..1)."""
        v, u = np.nonzero(self.valid)
        z = self.depth_m[v, u].astype(np.float64)
        k = self.intrinsics
        rect = np.stack(
            [(u - k.cx_px) / k.fx_px * z, (v - k.cy_px) / k.fy_px * z, z], axis=1
        )  # (M, 3) in the rectified frame
        points = rect @ self.rect_from_left  # R.T applied to row vectors: back to the sensor
        colours = self.rgb[v, u].astype(np.float32) / 255.0
        return points.astype(np.float32), colours

    def points_in_world(self, left_pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Valid pixels as world points, given the left sensor's world-to-camera pose."""
        cam, colours = self.points_in_left_camera()
        world = (cam.astype(np.float64) - left_pose.t_m) @ left_pose.R
        return world.astype(np.float32), colours


def compute_depth(
    left_rgb: np.ndarray,
    right_rgb: np.ndarray,
    left: Intrinsics,
    right: Intrinsics,
    right_from_left: Pose,
    config: StereoConfig | None = None,
    matcher: StereoMatcher | None = None,
) -> DepthMap:
    """Depth of one stereo pair (distorted sensor images, (H, W, 3) uint8 RGB).

    ``right_from_left`` maps left-sensor points to the right sensor: ``x_r = R x_l + t``.
    """
    check_images(left_rgb, right_rgb, left)
    cfg = config or StereoConfig.for_resolution(left.width_px)
    rect = rectifier(left, right, right_from_left, cfg.scale_for(left.width_px), cfg.rectify_alpha)
    left_r, right_r, inside_l, inside_r = rect.rectify(left_rgb, right_rgb)
    fb = rect.intrinsics.fx_px * rect.baseline_m  # depth_m = fb / disparity_px
    m = matcher or SgbmWlsMatcher(cfg)
    d_min, d_max = fb / cfg.max_depth_m, fb / cfg.min_depth_m
    disp = np.asarray(
        m.match(left_r, right_r, min_disparity_px=d_min, max_disparity_px=d_max), np.float32
    )
    if disp.shape != left_r.shape[:2]:
        raise StereoError(
            f"stereo matcher {m.name!r} returned disparity of shape {disp.shape}, expected "
            f"{left_r.shape[:2]}; fix the plug-in"
        )
    with np.errstate(invalid="ignore"):
        valid = inside_l & np.isfinite(disp) & (disp > 0)
    depth = np.full(disp.shape, np.nan, dtype=np.float32)
    depth[valid] = fb / disp[valid]
    valid &= (depth >= cfg.min_depth_m) & (depth <= cfg.max_depth_m)
    # the matched right pixel must come from inside the right sensor as well; a pixel whose
    # partner is beyond the right image's left edge has none (the left border's band, answered
    # only by ``StereoConfig.fill_left_border``) and is not checked
    w = disp.shape[1]
    x_r = np.rint(np.arange(w, dtype=np.float32)[None, :] - np.where(valid, disp, 0))
    beyond = x_r < 0
    x_r = np.clip(x_r, 0, w - 1).astype(np.intp)
    valid &= np.take_along_axis(inside_r, x_r, axis=1) | beyond
    depth[~valid] = np.nan
    log.debug("stereo %s: %.1f%% valid", m.name, 100 * valid.mean())
    return DepthMap(
        depth_m=depth,
        valid=valid,
        disparity_px=disp,
        intrinsics=rect.intrinsics,
        rect_from_left=rect.rect_from_left,
        baseline_m=rect.baseline_m,
        rgb=left_r,
    )


def check_images(left_rgb: np.ndarray, right_rgb: np.ndarray, left: Intrinsics) -> None:
    """Refuse images that are not an RGB pair of the calibrated size, naming the problem."""
    for side, img in (("left", left_rgb), ("right", right_rgb)):
        if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3:
            shape = getattr(img, "shape", type(img).__name__)
            raise StereoError(f"{side} image has shape {shape}; expected (H, W, 3) RGB")
        if img.dtype != np.uint8:
            raise StereoError(f"{side} image is {img.dtype}; expected uint8 RGB (0-255)")
    if left_rgb.shape != right_rgb.shape:
        raise StereoError(
            f"left and right images differ in size: {left_rgb.shape[1]}x{left_rgb.shape[0]} vs "
            f"{right_rgb.shape[1]}x{right_rgb.shape[0]}; both must come from one capture mode"
        )
    h, w = left_rgb.shape[:2]
    if (w, h) != (left.width_px, left.height_px):
        raise StereoError(
            f"images are {w}x{h} but the intrinsics are for {left.width_px}x{left.height_px}; "
            "use the calibration of the recorded resolution "
            "(protocol.formats.zed_conf.derive_intrinsics)"
        )


def rectifier(
    left: Intrinsics,
    right: Intrinsics,
    right_from_left: Pose,
    match_scale: float = 1.0,
    alpha: float = 0.0,
) -> StereoRectifier:
    """A cached ``StereoRectifier``: the maps are built once per calibration and reused for
    every frame."""
    key = right_from_left.matrix.tobytes()
    return _cached_rectifier(left, right, key, match_scale, alpha)


@functools.lru_cache(maxsize=8)
def _cached_rectifier(
    left: Intrinsics, right: Intrinsics, pose_key: bytes, match_scale: float, alpha: float
) -> StereoRectifier:
    m = np.frombuffer(pose_key, dtype=np.float64).reshape(4, 4)
    pose = Pose(R=m[:3, :3], t_m=m[:3, 3])
    return StereoRectifier(left, right, pose, match_scale=match_scale, alpha=alpha)
