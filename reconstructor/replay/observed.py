"""Observed versus inferred: per pixel of a render, how well the real cameras saw what it shows.

The paper asks for "uncertainty measures that distinguish directly observed content from
generative completion". A model holds both: Gaussians on surfaces the rig's cameras saw, and
Gaussians that hole filling, auxiliary views or the optimiser put where no camera looked
(behind a person, under the table, the far side of a head). This module tells them apart.

Per Gaussian, its **view count**: how many of the model's input cameras (the sensors it was
trained on, ``run_input_cameras``) saw its centre. A camera sees a centre when it is

1. in front of the camera (camera z above the model's near plane) and inside its image, and
2. not hidden behind the model's own surface there: the model is rendered into that camera
   (``visibility_width_px`` wide) and the centre counts when the pixel it falls on is barely
   covered (alpha under ``covered_alpha``: nothing opaque in front) or when its depth is at
   most the rendered depth there plus ``depth_tolerance_m + depth_tolerance_ratio * depth``
   (a surface is a few centimetres of Gaussians thick; the rendered depth is their blend).

A Gaussian is **well observed** when at least ``min_views`` cameras saw it. The default, 2, is
what a depth needs: two viewpoints (a stereo camera's two sensors, or two rigs). A Gaussian
seen by one sensor has only that ray's colour, its depth along the ray a guess; one seen by
none is inferred outright.

Per pixel, the **observed map** composites the 0/1 flag like colour through the same
rasterizer (so it follows exactly the blending of the render it describes):
``observed = sum_i w_i alpha_i T_i``, the share of the pixel's colour that comes from
well-observed Gaussians. What shows the background (the transmittance left over) counts as not
observed, so the map is in [0, 1] and 0 where the model is empty. A pixel, a frame or a
sightline target with an observed share under ``well_observed_share`` rests on inferred
content. The second channel composites the view counts themselves (``views``: the mean number
of cameras that saw what the pixel shows).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from protocol.camera import Camera
from protocol.formats.rig_calibration import RigCalibration
from reconstructor.errors import ObservedError
from reconstructor.raster import RasterConfig, rasterize
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ObservedConfig:
    """How view counts and the observed map are made (see the module docstring).

    Attributes:
        min_views: cameras that must see a Gaussian for it to count as well observed (>= 1).
        depth_tolerance_m, depth_tolerance_ratio: how far behind the rendered depth of a camera
            a centre may lie and still count as seen: ``m + ratio * depth``.
        covered_alpha: a pixel with less rendered alpha hides nothing behind it.
        visibility_width_px: width the input cameras are rendered at for the depth test (the
            test is per Gaussian centre, so a quarter of SVGA loses little and costs 1/16).
        well_observed_share: a pixel (frame, target) whose observed share is below this rests
            on inferred content; replay and sightline flag it.
    """

    min_views: int = 2
    depth_tolerance_m: float = 0.05
    depth_tolerance_ratio: float = 0.02
    covered_alpha: float = 0.5
    visibility_width_px: int = 240
    well_observed_share: float = 0.5

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ObservedError:
            return ObservedError(f"ObservedConfig.{name} = {getattr(self, name)!r}: {why}")

        if isinstance(self.min_views, bool) or not isinstance(self.min_views, int):
            raise bad("min_views", "give a whole number of cameras")
        if self.min_views < 1:
            raise bad("min_views", "must be at least 1")
        if not (self.depth_tolerance_m >= 0 and self.depth_tolerance_ratio >= 0):
            raise bad("depth_tolerance_m", "tolerances must be >= 0")
        if not 0 < self.covered_alpha <= 1:
            raise bad("covered_alpha", "must be in (0, 1]")
        if not 16 <= self.visibility_width_px <= 8192:
            raise bad("visibility_width_px", "give 16 to 8192 px")
        if not 0 < self.well_observed_share <= 1:
            raise bad("well_observed_share", "must be in (0, 1]")


@dataclass(frozen=True)
class ObservedRender:
    """The observed map of one camera (float32 numpy arrays, (H, W)).

    Attributes:
        observed: share of each pixel's colour from well-observed Gaussians, in [0, 1].
        views: alpha-weighted mean view count of what the pixel shows (0 where empty).
        alpha: the render's alpha (1 - transmittance).
    """

    observed: np.ndarray
    views: np.ndarray
    alpha: np.ndarray

    def well_observed(self, config: ObservedConfig) -> np.ndarray:
        """(H, W) bool: pixels marked well observed (the rest are inferred)."""
        return self.observed >= config.well_observed_share

    @property
    def share(self) -> float:
        """The frame's observed share: the mean of ``observed``."""
        return float(self.observed.mean())


def pinhole_at_width(camera: Camera, width_px: int) -> Camera:
    """The camera as the training views see it (undistorted pinhole), scaled down to at most
    ``width_px`` wide with pixel centres kept (x' = (x + 0.5) s - 0.5, as view_from_image)."""
    k = camera.intrinsics.undistorted()
    if k.width_px <= width_px:
        return replace(camera, intrinsics=k)
    s = width_px / k.width_px
    h = max(1, round(k.height_px * s))
    sy = h / k.height_px
    small = replace(
        k, width_px=width_px, height_px=h, fx_px=k.fx_px * s, fy_px=k.fy_px * sy,
        cx_px=(k.cx_px + 0.5) * s - 0.5, cy_px=(k.cy_px + 0.5) * sy - 0.5,
    )  # fmt: skip
    return replace(camera, intrinsics=small)


def _raster(
    g: Gaussians, colors: torch.Tensor, camera: Camera, raster: RasterConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image (H, W, 3), alpha (H, W), depth_m (H, W)) numpy arrays of ``colors`` composited
    over black, through the same rasterizer as the colour render."""
    k = camera.intrinsics.undistorted()
    dev = g.means_m.device
    with torch.no_grad():
        out = rasterize(
            g.means_m.detach(), g.quats_wxyz.detach(), g.log_scales.detach(),
            g.opacity_logits.detach(), colors.to(dev),
            torch.from_numpy(camera.pose.matrix.astype(np.float32)),
            torch.from_numpy(k.K.astype(np.float32)), k.width_px, k.height_px,
            torch.zeros(3, device=dev), raster,
        )  # fmt: skip
    return out.image.cpu().numpy(), out.alpha.cpu().numpy(), out.depth_m.cpu().numpy()


def seen_by(
    g: Gaussians, camera: Camera, raster: RasterConfig, config: ObservedConfig
) -> np.ndarray:
    """(N,) bool: which Gaussians' centres ``camera`` sees, by the depth the model renders
    there (the module docstring has the test)."""
    cam = pinhole_at_width(camera, config.visibility_width_px)
    _, alpha, depth = _raster(g, torch.zeros(g.num, 3), cam, raster)
    k = cam.intrinsics
    xyz = cam.pose.transform(g.means_m.detach().cpu().double().numpy())
    z = xyz[:, 2]
    front = (z > raster.near_m) & (z < raster.far_m)
    zs = np.where(front, z, 1.0)
    u = np.round(k.fx_px * xyz[:, 0] / zs + k.cx_px)
    v = np.round(k.fy_px * xyz[:, 1] / zs + k.cy_px)
    inside = front & (u >= 0) & (u < k.width_px) & (v >= 0) & (v < k.height_px)
    idx = np.nonzero(inside)[0]
    ui, vi = u[idx].astype(int), v[idx].astype(int)
    d = depth[vi, ui]
    unhidden = (alpha[vi, ui] < config.covered_alpha) | (
        z[idx] <= d + config.depth_tolerance_m + config.depth_tolerance_ratio * d
    )
    seen = np.zeros(g.num, dtype=bool)
    seen[idx[unhidden]] = True
    return seen


def observation_counts(
    g: Gaussians,
    cameras: Sequence[Camera],
    raster: RasterConfig,
    config: ObservedConfig | None = None,
) -> np.ndarray:
    """(N,) int32: how many of ``cameras`` (the model's input cameras) see each Gaussian."""
    cfg = config or ObservedConfig()
    counts = np.zeros(g.num, dtype=np.int32)
    for camera in cameras:
        counts += seen_by(g, camera, raster, cfg)
    if g.num:
        well = int((counts >= cfg.min_views).sum())
        log.info(
            "%d of %d Gaussians seen by at least %d of %d input cameras",
            well, g.num, cfg.min_views, len(cameras),
        )  # fmt: skip
    return counts


def observed_map(
    g: Gaussians,
    counts: np.ndarray,
    camera: Camera,
    raster: RasterConfig,
    config: ObservedConfig | None = None,
) -> ObservedRender:
    """The observed map of ``camera`` (its undistorted pinhole, at its own size): the
    well-observed flag and the view count composited like colour, with the render's blending."""
    cfg = config or ObservedConfig()
    if len(counts) != g.num:
        raise ValueError(f"counts has {len(counts)} entries for {g.num} Gaussians")
    c = torch.from_numpy(np.asarray(counts, dtype=np.float32))
    colors = torch.stack([(c >= cfg.min_views).float(), c, torch.zeros_like(c)], dim=1)
    image, alpha, _ = _raster(g, colors, camera, raster)
    views = np.where(alpha > 1e-3, image[:, :, 1] / np.maximum(alpha, 1e-3), 0.0)
    return ObservedRender(
        observed=np.clip(image[:, :, 0], 0.0, 1.0).astype(np.float32),
        views=views.astype(np.float32),
        alpha=alpha,
    )


INFERRED_TINT_RGB = np.array([255.0, 0.0, 200.0])  # magenta: no colour of an OR scene


def overlay(rgb: np.ndarray, observed: np.ndarray, strength: float = 0.6) -> np.ndarray:
    """(H, W, 3) uint8: ``rgb`` tinted magenta in proportion to its inferred share."""
    a = (strength * (1.0 - np.clip(observed, 0.0, 1.0)))[:, :, None]
    return (rgb.astype(np.float32) * (1 - a) + INFERRED_TINT_RGB * a + 0.5).astype(np.uint8)


def run_input_cameras(run_dir: Path) -> list[Camera]:
    """The cameras a reconstruction run trained on, from what the run saved: the sensor names
    of ``summary.json``'s ``train_views`` in its ``calibration.toml`` (a case keeps both in
    ``runs/<timestamp>/``)."""
    summary, cal = run_dir / "summary.json", run_dir / "calibration.toml"
    for path in (summary, cal):
        if not path.is_file():
            raise ObservedError(
                f"{path} is missing: the cameras this model was trained on are unknown, so "
                "what they observed cannot be told; rerun its reconstruction, or leave out "
                "the observed-versus-inferred option"
            )
    try:
        names = json.loads(summary.read_text())["train_views"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ObservedError(f"{summary} has no readable train_views list ({exc})") from None
    sensors = {s.name: s.camera for s in RigCalibration.read(cal).sensors}
    unknown = [n for n in names if n not in sensors]
    if unknown or not names:
        raise ObservedError(
            f"{summary} names training views {unknown or names} that {cal} does not hold; "
            "the run folder is inconsistent: rerun its reconstruction"
        )
    return [sensors[n] for n in names]
