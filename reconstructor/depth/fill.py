"""Filling the holes stereo leaves on blank surfaces, so that every surface gets Gaussians.

Block matching cannot match a blank wall or ceiling (the sim's paint, and real ones), and the
stereo stage rightly leaves them without depth. But the splats are never densified (the paper's
schedule), so a surface without initial points stays a hole in every render. This stage
spreads the confident disparity into the holes with an edge-aware smoother guided by the
image (normalised convolution with OpenCV's fast global smoother): inside a blank wall the
disparity of its textured rims (corners, doors, fittings) spreads across, and colour edges stop
it. A filled pixel is kept when enough confident disparity reached it (``min_weight``) and its
depth is in range. Filled points are marked so callers can give them less trust.

Disparity, not depth, is smoothed: a plane's disparity is linear in the image, its depth is not.

What is still a hole after that (a wall or ceiling with no textured rim in view) is seen through
to the room's shell when the room's box is known (``room_bounds_m``, measured once per site): the
pixel's ray is cut where it leaves the box and a point there takes the pixel's colour
(``room_shell``). The cut is on the wall itself (``shell_inset_m = 0``): the wall a camera hangs
on is seen at a grazing angle, so an inset of 2 cm put it 15-27 % too near for a camera 8 cm from
its wall, and the held-out views beside it showed the misplaced wall. In an OR the surfaces
stereo cannot match are mostly the walls and ceiling themselves, so the shell is their right
depth; anything else left blank sits in front of it and training moves those Gaussians where the
other views need them.

With the room's box known, a filled pixel near its shell goes onto the shell (``shell_snap``: at
least half the shell's depth along its ray). The smoother spreads a blank wall's disparity from
everything around it, so a wall behind a person or a cabinet comes out bent toward them:
measured on the sim (four cameras, intraoperative), only 37 % of the filled points were within
3 % of the true depth and 47 % lay more than 5 % in front of it, floating in the room where
every other view sees through them. Snapped at 0.5: 77 % within 3 %, 3 % in front (18 % behind:
blank objects nearer than the wall, which training recolours from the views that see them).
At 0.3: 69 %, 15 % and 12 %; near-field w/o refinement 32.1 dB at 0.3, 32.2 at 0.5, 30.6 at 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from protocol.camera import Pose
from reconstructor.depth.stereo import DepthMap
from reconstructor.errors import ReconstructConfigError


@dataclass(frozen=True, kw_only=True)
class FillConfig:
    enabled: bool = True
    smoothness: float = 2000.0  # the smoother's lambda: how far disparity spreads
    sigma_color: float = 6.0  # colour difference (0..255) that stops it
    min_weight: float = 0.05  # share of confident disparity that must reach a filled pixel
    stride_px: int = 2  # keep every n-th filled pixel in each direction: blank walls need few
    room_shell: bool = True  # points on the room's box for what is still a hole (needs bounds)
    shell_stride_px: int = 4
    shell_inset_m: float = 0.0  # cut the rays this far before the walls
    # a filled pixel at z >= (1 - shell_snap) * its shell depth goes onto the shell: the smoother
    # bends a blank wall's disparity toward its neighbours' (0: off; module docstring)
    shell_snap: float = 0.5

    def __post_init__(self) -> None:
        if self.smoothness <= 0 or self.sigma_color <= 0:
            raise ReconstructConfigError(
                f"fill: smoothness and sigma_color must be positive, got {self.smoothness}, "
                f"{self.sigma_color}"
            )
        if not 0 < self.min_weight < 1:
            raise ReconstructConfigError(f"fill.min_weight={self.min_weight}: must be in (0, 1)")
        if self.stride_px < 1:
            raise ReconstructConfigError(f"fill.stride_px={self.stride_px}: must be >= 1")
        if self.shell_stride_px < 1:
            raise ReconstructConfigError(
                f"fill.shell_stride_px={self.shell_stride_px}: must be >= 1"
            )
        if self.shell_inset_m < 0:
            raise ReconstructConfigError(f"fill.shell_inset_m={self.shell_inset_m}: must be >= 0")
        if not 0 <= self.shell_snap < 1:
            raise ReconstructConfigError(f"fill.shell_snap={self.shell_snap}: must be in [0, 1)")


def fill_disparity(
    depth: DepthMap, config: FillConfig, *, strided: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """(filled disparity (H, W) float32, mask of the pixels filled here (H, W) bool; only every
    ``stride_px``-th pixel unless ``strided`` is False)."""
    fb = depth.intrinsics.fx_px * depth.baseline_m
    valid = depth.valid & np.isfinite(depth.depth_m)
    disp = np.where(valid, fb / np.where(valid, depth.depth_m, 1.0), 0.0).astype(np.float32)
    weight = valid.astype(np.float32)
    guide = depth.rgb

    def smooth(x: np.ndarray) -> np.ndarray:
        return cv2.ximgproc.fastGlobalSmootherFilter(
            guide, x, config.smoothness, config.sigma_color
        )

    num, den = smooth(disp * weight), smooth(weight)
    with np.errstate(invalid="ignore", divide="ignore"):
        filled = np.where(den > config.min_weight, num / den, np.nan).astype(np.float32)
    mask = ~valid & np.isfinite(filled) & (filled > 0)
    if not strided:
        return filled, mask
    sub = np.zeros_like(mask)
    sub[:: config.stride_px, :: config.stride_px] = True
    return filled, mask & sub


def fill_points_in_world(
    depth: DepthMap,
    left_pose: Pose,
    config: FillConfig,
    *,
    min_depth_m: float,
    max_depth_m: float,
    room_box_m: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of the filled pixels, then of the room shell behind what is
    still a hole when ``room_box_m`` (lo, hi) is given (none when disabled)."""
    empty = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    if not config.enabled:
        return empty
    filled, full_mask = fill_disparity(depth, config, strided=False)
    fb = depth.intrinsics.fx_px * depth.baseline_m
    shell = config.room_shell and room_box_m is not None
    lo = hi = centre = np.zeros(3)
    if shell:
        assert room_box_m is not None
        lo = np.asarray(room_box_m[0], np.float64) + config.shell_inset_m
        hi = np.asarray(room_box_m[1], np.float64) - config.shell_inset_m
        centre = left_pose.centre_m
        shell = bool(np.all(centre > lo) and np.all(centre < hi))
    v, u = np.nonzero(full_mask)
    z = fb / filled[v, u].astype(np.float64)
    keep = (z >= min_depth_m) & (z <= max_depth_m)
    rays = _rect_rays(depth, u, v)
    if shell:
        # A fill that puts a pixel behind the room's walls is wrong: it spread the disparity of
        # a far surface (the floor) into a near blank one (the wall the camera hangs on, seen at
        # a grazing angle). Such a pixel, and one filled out of the depth range, is left to the
        # shell, which has the wall's depth.
        exit_z = ray_box_exit(centre, _to_world(rays, depth, left_pose) - centre, lo, hi)
        keep &= z <= exit_z + config.shell_inset_m
        full_mask[v[~keep], u[~keep]] = False
        z = np.where(keep & (z >= (1.0 - config.shell_snap) * exit_z), exit_z, z)
    keep &= (v % config.stride_px == 0) & (u % config.stride_px == 0)
    v, u, z, rays = v[keep], u[keep], z[keep], rays[keep]
    points = [_to_world(rays * z[:, None], depth, left_pose)]
    colours = [depth.rgb[v, u].astype(np.float32) / 255.0]
    if shell:
        hole = ~(depth.valid & np.isfinite(depth.depth_m)) & ~full_mask
        sub = np.zeros_like(hole)
        sub[:: config.shell_stride_px, :: config.shell_stride_px] = True
        v, u = np.nonzero(hole & sub)
        if len(v):
            rays = _rect_rays(depth, u, v)
            dirs = _to_world(rays, depth, left_pose) - centre  # rays as world directions
            dist = ray_box_exit(centre, dirs, lo, hi)
            points.append((centre + dirs * dist[:, None]).astype(np.float32))
            colours.append(depth.rgb[v, u].astype(np.float32) / 255.0)
    return np.concatenate(points).astype(np.float32), np.concatenate(colours)


def ray_box_exit(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """(N,) ray parameter where rays ``origin + s * dirs`` (dirs (N, 3)) leave the box [lo, hi]
    that holds ``origin``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(dirs > 0, hi, lo)
        s = np.where(dirs != 0, (bound - origin) / dirs, np.inf)
    return s.min(axis=1)


def _rect_rays(depth: DepthMap, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) rays at z = 1 of rectified pixels (u, v)."""
    k = depth.intrinsics
    return np.stack([(u - k.cx_px) / k.fx_px, (v - k.cy_px) / k.fy_px, np.ones(len(u))], axis=1)


def _to_world(rect_points: np.ndarray, depth: DepthMap, left_pose: Pose) -> np.ndarray:
    """Points in the rectified left frame -> world."""
    cam = rect_points @ depth.rect_from_left
    return (cam - left_pose.t_m) @ left_pose.R
