"""Reference-guided correction: warp the reference image into the auxiliary view by depth.

No weights, CPU only, vectorised numpy/OpenCV (~100 calls per reconstruction at 960x600).
For one ``RefineRequest``:

1. every auxiliary pixel with rendered depth is unprojected with the auxiliary camera and
   projected into the reference camera (both ideal pinholes; the intrinsics are scaled when an
   image is a resized copy of its camera's frame);
2. the reference image is sampled there (``cv2.remap``, bilinear). The warp is valid where the
   point lands inside the reference image and its mask, in front of the reference camera, and
   is not occluded: its reference-camera depth agrees with ``reference_depth_m`` (the model seen
   from the reference, sampled nearest) within ``depth_tolerance`` (relative);
3. a valid warp replaces the render; elsewhere the render stays. Pixels that are neither (render
   alpha below ``min_alpha`` and no valid warp) are holes, filled by Telea inpainting from the
   corrected image (on a copy resized by ``inpaint_scale``: same quality, a fraction of the time);
4. optionally (``use_guided_filter``, off: it did not help on the sim) the seams between
   warped, rendered and inpainted regions are smoothed with a guided filter
   (``cv2.ximgproc.guidedFilter``) guided by the corrected image, only in a band around them.

The returned mask holds the warped pixels, the confidently rendered ones when
``supervise_rendered`` is set, and the inpainted ones when ``supervise_inpainted`` is set. The
defaults come from ``bench/bench_refiners.py`` (numbers in ``BENCHMARKS.md``, "Refiners").
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.camera import Camera
from reconstructor.errors import ReconstructConfigError
from reconstructor.refine.base import Refined, Refiner, RefineRequest

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class GuidedConfig:
    """Settings of ``GuidedRefiner``; each one measured in ``bench/bench_refiners.py``."""

    # |z_in_reference - reference_depth| <= depth_tolerance * reference_depth: not occluded
    depth_tolerance: float = 0.03
    min_alpha: float = 0.5  # render alpha below this is a hole (nothing confident rendered)
    warp_weight: float = 1.0  # where both exist: weight of the warp against a confident render
    use_inpaint: bool = True  # fill holes that no valid warp covers (Telea)
    inpaint_radius_px: int = 3  # at the inpainting scale
    inpaint_scale: float = 0.25  # inpaint a copy resized by this factor (Telea is slow at 1)
    use_guided_filter: bool = False  # smooth the seams between warped/rendered/inpainted pixels
    guided_filter_radius_px: int = 4
    guided_filter_eps: float = 1e-3  # on [0, 1] intensities: ~0.03 grey levels of edge contrast
    seam_band_px: int = 3  # half-width of the band around seams that the filter may change
    supervise_inpainted: bool = False  # let the loss use inpainted pixels too
    # let the loss use rendered pixels no warp replaced: they repeat the model as it was when
    # the auxiliary views were made and hold it there for the rest of the schedule (near-field,
    # 500 + 1500 steps: 26.2 dB with them, 28.9 without; EVALUATION.md)
    supervise_rendered: bool = False

    def __post_init__(self) -> None:
        def bad(field: str, value: object, why: str) -> ReconstructConfigError:
            return ReconstructConfigError(f"GuidedConfig.{field}={value!r}: {why}")

        if not 0.0 < self.depth_tolerance <= 1.0:
            raise bad("depth_tolerance", self.depth_tolerance, "must be in (0, 1] (relative)")
        if not 0.0 < self.min_alpha <= 1.0:
            raise bad("min_alpha", self.min_alpha, "must be in (0, 1]")
        if not 0.0 <= self.warp_weight <= 1.0:
            raise bad("warp_weight", self.warp_weight, "must be in [0, 1]")
        if not 1 <= self.inpaint_radius_px <= 32:
            raise bad("inpaint_radius_px", self.inpaint_radius_px, "must be from 1 to 32")
        if not 1 <= self.guided_filter_radius_px <= 32:
            raise bad(
                "guided_filter_radius_px", self.guided_filter_radius_px, "must be from 1 to 32"
            )
        if not 0.05 <= self.inpaint_scale <= 1.0:
            raise bad("inpaint_scale", self.inpaint_scale, "must be in [0.05, 1]")
        if not self.guided_filter_eps > 0.0:
            raise bad("guided_filter_eps", self.guided_filter_eps, "must be positive")
        if not 1 <= self.seam_band_px <= 64:
            raise bad("seam_band_px", self.seam_band_px, "must be from 1 to 64")
        for name in (
            "use_inpaint",
            "use_guided_filter",
            "supervise_inpainted",
            "supervise_rendered",
        ):
            if not isinstance(getattr(self, name), bool):
                raise bad(name, getattr(self, name), "must be true or false")


# Region labels of the corrected image, for seams and the mask.
RENDERED, WARPED, INPAINTED, EMPTY = 0, 1, 2, 3


class GuidedRefiner(Refiner):
    """Reference-guided correction (module docstring); ``GuidedConfig`` holds its settings."""

    name = "guided"
    needs_weights = False

    def __init__(self, config: GuidedConfig | None = None) -> None:
        if config is not None and not isinstance(config, GuidedConfig):
            raise ReconstructConfigError(
                f"the guided refiner takes a GuidedConfig, got a {type(config).__name__}"
            )
        self.config = config if config is not None else GuidedConfig()

    def describe(self) -> str:
        fields = ", ".join(
            f"{f.name}={getattr(self.config, f.name)}" for f in dataclasses.fields(self.config)
        )
        return f"{self.name}({fields})"

    def refine(self, request: RefineRequest) -> Refined:
        image, labels = refine_guided(request, self.config)
        mask = labels == WARPED
        if self.config.supervise_rendered:
            mask |= labels == RENDERED
        if self.config.supervise_inpainted:
            mask |= labels == INPAINTED
        return Refined(image=image, mask=mask)


def refine_guided(request: RefineRequest, cfg: GuidedConfig) -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) float32 corrected image in [0, 1], (H, W) uint8 region labels).

    Labels: ``RENDERED`` (the render kept), ``WARPED`` (a valid warp), ``INPAINTED``, ``EMPTY``
    (a hole left unfilled: inpainting off, or nothing to inpaint from).
    """
    check_request(request)
    rendered = np.asarray(request.rendered, dtype=np.float32)
    alpha = np.asarray(request.rendered_alpha, dtype=np.float32)
    confident = alpha >= cfg.min_alpha
    warped, valid = warp_reference(request, cfg.depth_tolerance)

    out = rendered.copy()  # a new array: the inputs stay intact
    # a valid warp replaces the render; a confident render may keep a share of its colour
    _copy_where(warped, valid, out)
    if cfg.warp_weight < 1.0:
        both = valid & confident
        wt = np.float32(cfg.warp_weight)
        out[both] = wt * warped[both] + (1 - wt) * rendered[both]
    labels = np.where(confident, np.uint8(RENDERED), np.uint8(EMPTY))
    labels[valid] = WARPED

    holes = labels == EMPTY
    if cfg.use_inpaint and holes.any() and not holes.all():
        out = inpaint_holes(out, holes, cfg.inpaint_radius_px, cfg.inpaint_scale)
        labels[holes] = INPAINTED
    else:
        np.copyto(out, np.float32(0), where=holes[..., None])

    if cfg.use_guided_filter:
        out = smooth_seams(out, labels, cfg)
    np.clip(out, 0.0, 1.0, out=out)
    return out, labels


def _copy_where(src: np.ndarray, where: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``dst[where] = src[where]`` in place (OpenCV's masked copy: 3x faster than numpy's)."""
    cv2.copyTo(src, where.astype(np.uint8), dst)
    return dst


def check_request(request: RefineRequest) -> None:
    """Raise ValueError naming the array whose shape does not fit the others."""
    h, w = np.shape(request.rendered)[:2]
    hr, wr = np.shape(request.reference)[:2]
    expected = {
        "rendered": (np.shape(request.rendered), (h, w, 3)),
        "rendered_alpha": (np.shape(request.rendered_alpha), (h, w)),
        "rendered_depth_m": (np.shape(request.rendered_depth_m), (h, w)),
        "reference": (np.shape(request.reference), (hr, wr, 3)),
        "reference_mask": (np.shape(request.reference_mask), (hr, wr)),
        "reference_depth_m": (np.shape(request.reference_depth_m), (hr, wr)),
    }
    for name, (got, want) in expected.items():
        if tuple(got) != want:
            raise ValueError(f"RefineRequest.{name} has shape {tuple(got)}, expected {want}")


def scaled_K(camera: Camera, shape_hw: tuple[int, int]) -> np.ndarray:
    """The 3x3 camera matrix of ``camera`` for an image of ``shape_hw`` (a resized frame)."""
    intr = camera.intrinsics
    sx = shape_hw[1] / intr.width_px
    sy = shape_hw[0] / intr.height_px
    K = intr.K.copy()
    # pixel centres stay at integer coordinates: c' = (c + 0.5) * s - 0.5
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def warp_reference(request: RefineRequest, depth_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) float32 reference sampled at each auxiliary pixel's reprojection, (H, W) bool
    valid): inside the reference and its mask, in front of it, and not occluded."""
    depth = np.asarray(request.rendered_depth_m, dtype=np.float32)
    h, w = depth.shape
    ref = np.asarray(request.reference, dtype=np.float32)
    hr, wr = ref.shape[:2]
    K_a = scaled_K(request.camera, (h, w))
    K_r = scaled_K(request.reference_camera, (hr, wr))
    pa, pr = request.camera.pose, request.reference_camera.pose
    R_rel = pr.R @ pa.R.T  # auxiliary camera frame -> reference camera frame
    t_rel = pr.t_m - R_rel @ pa.t_m
    # reference pixel, homogeneous: d * (K_r R_rel K_a^-1) [u v 1] + K_r t_rel
    M = K_r @ R_rel @ np.linalg.inv(K_a)
    b = K_r @ t_rel
    us = np.arange(w, dtype=np.float32)
    vs = np.arange(h, dtype=np.float32)[:, None]
    X, Y, Z = (
        depth * ((M[i, 0] * us + M[i, 2]).astype(np.float32) + np.float32(M[i, 1]) * vs)
        + np.float32(b[i])
        for i in range(3)
    )
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv_z = np.float32(1) / Z
        map_x = X * inv_z
        map_y = Y * inv_z
        # no depth (0 or NaN), or behind the reference: out of the image, so remap gives 0
        bad = ~((depth > 0) & (Z > 1e-6) & np.isfinite(map_x) & np.isfinite(map_y))
    map_x[bad] = -10.0
    map_y[bad] = -10.0
    # the mask folded into the depth: one lookup; nearest, since interpolating depth across an
    # occluding edge invents surfaces in between
    ref_depth = np.asarray(request.reference_depth_m, dtype=np.float32)
    ref_depth = np.where(np.asarray(request.reference_mask, dtype=bool), ref_depth, np.float32(0))
    d_ref = cv2.remap(ref_depth, map_x, map_y, cv2.INTER_NEAREST, borderValue=0.0)
    with np.errstate(invalid="ignore"):
        valid = (d_ref > 0) & (np.abs(Z - d_ref) <= np.float32(depth_tolerance) * d_ref)
    warped = cv2.remap(ref, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return warped.reshape(h, w, -1), valid


def inpaint_holes(
    image: np.ndarray, holes: np.ndarray, radius_px: int, scale: float = 1.0
) -> np.ndarray:
    """``image`` (H, W, 3) float32 with the ``holes`` pixels filled by Telea inpainting.

    With ``scale`` < 1 the inpainting runs on a copy resized by ``scale`` (the known pixels
    averaged without the holes) and the fill is resized back: Telea's cost grows with hole area
    times radius squared, and a fill carries no detail worth the full resolution. OpenCV
    inpaints 3-channel images only as 8 bits; the quantisation touches only the holes.
    """
    h, w = holes.shape
    known = (~holes).astype(np.float32)
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        weight = cv2.resize(known, size, interpolation=cv2.INTER_AREA)
        summed = cv2.resize(image * known[..., None], size, interpolation=cv2.INTER_AREA)
        small = summed / np.maximum(weight, 1e-6)[..., None]
        small_holes = weight < 1e-3
    else:
        small, small_holes = image, holes
    img8 = np.clip(small * 255.0 + 0.5, 0, 255).astype(np.uint8)
    filled = cv2.inpaint(img8, small_holes.astype(np.uint8), radius_px, cv2.INPAINT_TELEA)
    filled_f = filled.astype(np.float32) / np.float32(255)
    if scale < 1.0:
        filled_f = np.asarray(cv2.resize(filled_f, (w, h), interpolation=cv2.INTER_LINEAR))
    return _copy_where(filled_f, holes, image.copy())


def seam_band(labels: np.ndarray, band_px: int) -> np.ndarray:
    """(H, W) bool: pixels within ``band_px`` of a boundary between two region labels."""
    k = np.ones((3, 3), np.uint8)
    edge = cv2.dilate(labels, k) != cv2.erode(labels, k)
    if not edge.any():
        return edge
    size = 2 * band_px + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.dilate(edge.astype(np.uint8), disk) > 0


def smooth_seams(image: np.ndarray, labels: np.ndarray, cfg: GuidedConfig) -> np.ndarray:
    """``image`` with a guided filter applied in the seam band only, guided by its luma.

    A grey guide, not the colour one: OpenCV's colour guided filter changed flat and black
    regions of a render by up to 0.9 (of 1) at small ``eps`` (its 3x3 covariance is near
    singular there), and costs 2.5x more.
    """
    band = seam_band(labels, cfg.seam_band_px)
    if not band.any():
        return image
    # filter only the band's bounding box (plus the filter's reach): seams are usually sparse
    ys, xs = np.nonzero(band)
    r = cfg.guided_filter_radius_px
    y0, y1 = max(0, int(ys.min()) - r), min(image.shape[0], int(ys.max()) + r + 1)
    x0, x1 = max(0, int(xs.min()) - r), min(image.shape[1], int(xs.max()) + r + 1)
    crop = np.ascontiguousarray(image[y0:y1, x0:x1])
    guide = cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY)
    filtered = cv2.ximgproc.guidedFilter(guide, crop, r, cfg.guided_filter_eps)
    out = image.copy()
    _copy_where(filtered, band[y0:y1, x0:x1], out[y0:y1, x0:x1])
    return out
