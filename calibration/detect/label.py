"""Which detected sphere is which: the wand's first, middle and last sphere, in one view and then
in a ZED's own stereo pair.

One view (``label_wand``): the three spheres are collinear in the *undistorted* image, so the
middle one lies between the other two on a straight line; the ends are told apart by the unequal
spacing. Three points have no projective invariant, so the spacing is checked with the exact
perspective model instead of the raw image ratio: for a hypothesis "this end is the first
sphere", the rays of the three centres and the known positions along the rod fix the three
depths (``_wand_depths``); those must be positive and agree with each sphere's own distance from
its apparent size (``SphereBlob.distance_m``). Blobs without a distance fall back to the image
ratio of the segments against the spacing, with Vicon's relative tolerance of 0.2.

Stereo (``label_stereo``): each ZED X triangulates the three spheres metrically with its factory
calibration. Of the four ways to pair the ends of the left and right labelling, the physical one
reprojects well and reproduces the wand's centre distances; if it is the flipped labelling in a
view, that view is relabelled. Anything else is rejected with a reason, and ``RejectionCounter``
keeps the totals per reason.

The distance tolerance grows with the triangulation's own uncertainty (``StereoConfig``): with a
12 cm baseline, 0.1 px of disparity is 14 mm of depth at 3.5 m. So one frame with the wand along
the line of sight at 4 m cannot tell a 150 mm segment from a 200 mm one; a wrong wand file shows
in the frames where the wand lies across the view, and in the distances' statistics.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.detect.config import SphereBlob
from calibration.detect.detector import SphereDetector
from protocol.camera import undistort_to_normalized
from protocol.formats.wand import WandSpec
from protocol.formats.zed_conf import StereoCalibration

FEWER_THAN_3 = "fewer than 3 spheres"
NOT_COLLINEAR = "not collinear"
RATIO_MISMATCH = "ratio mismatch"
AMBIGUOUS = "ambiguous"
NOT_IN_BOTH_VIEWS = "not labelled in both views"
VIEWS_DISAGREE = "left and right views disagree"
WAND_MISMATCH = "wand distances mismatch"


@dataclass(frozen=True, kw_only=True)
class LabelConfig:
    """Tolerances of ``label_wand``."""

    collinear_tol_px: float = 1.5  # middle centre's distance from the line through the ends
    ratio_tol: float = 0.2  # relative, on the image segment ratio (blobs without a distance)
    distance_tol: float = 0.15  # relative, perspective depths vs the spheres' own distances
    ambiguity_margin: float = 0.5  # the runner-up's cost must exceed the best's by this much
    max_blobs: int = 12  # best-scoring blobs considered

    def __post_init__(self) -> None:
        for name in ("collinear_tol_px", "ratio_tol", "distance_tol", "ambiguity_margin"):
            v = getattr(self, name)
            if not v > 0:
                raise ValueError(f"LabelConfig.{name}={v} must be positive")
        if self.max_blobs < 3:
            raise ValueError(f"LabelConfig.max_blobs={self.max_blobs} must be at least 3")


@dataclass(frozen=True, kw_only=True)
class StereoConfig:
    """Tolerances of ``label_stereo``.

    A centre distance passes within ``max(distance_tol_mm, distance_tol_frac * distance)`` plus
    ``n_sigma`` times its uncertainty from a disparity error of ``disparity_sigma_px``. The
    second term is what a 12 cm baseline costs: depth error ``Z^2 / (f b)`` per px of disparity,
    about 18 mm at 4 m for 0.1 px, which lands on a distance only as far as the wand points
    along the line of sight. Set ``disparity_sigma_px=0`` for the plain metric tolerance.
    """

    distance_tol_mm: float = 10.0
    distance_tol_frac: float = 0.03
    disparity_sigma_px: float = 0.08
    n_sigma: float = 3.0
    max_reprojection_px: float = 1.5

    def __post_init__(self) -> None:
        if self.disparity_sigma_px < 0 or self.n_sigma < 0:
            raise ValueError(
                f"StereoConfig disparity_sigma_px={self.disparity_sigma_px} and "
                f"n_sigma={self.n_sigma} must not be negative"
            )
        for name in ("distance_tol_mm", "distance_tol_frac", "max_reprojection_px"):
            v = getattr(self, name)
            if not v > 0:
                raise ValueError(f"StereoConfig.{name}={v} must be positive")


@dataclass(frozen=True, kw_only=True, eq=False)
class LabelResult:
    """One view's labelling: ``points_px`` (3, 2) distorted pixels of the sphere centres in wand
    order (first, middle, last), or ``reason`` why the frame was rejected."""

    points_px: np.ndarray | None = None
    blobs: tuple[SphereBlob, ...] = ()
    reason: str | None = None
    cost: float = float("nan")
    depths_m: np.ndarray | None = None  # (3,) distance of each centre implied by the wand

    @property
    def ok(self) -> bool:
        return self.points_px is not None

    def flipped(self) -> LabelResult:
        """The same spheres labelled the other way round."""
        if self.points_px is None:
            return self
        return LabelResult(
            points_px=self.points_px[::-1].copy(),
            blobs=self.blobs[::-1],
            reason=self.reason,
            cost=self.cost,
            depths_m=None if self.depths_m is None else self.depths_m[::-1].copy(),
        )

    @classmethod
    def rejected(cls, reason: str) -> LabelResult:
        return cls(reason=reason)


@dataclass(frozen=True, kw_only=True, eq=False)
class StereoLabel:
    """A ZED's labelled pair: pixels (3, 2) per side in wand order, the spheres triangulated in
    the left sensor's frame (m), their centre distances (first-middle, middle-last, first-last,
    mm) and whether a view's labelling had to be flipped; or ``reason`` for the rejection."""

    left_px: np.ndarray | None = None
    right_px: np.ndarray | None = None
    points_left_m: np.ndarray | None = None
    distances_mm: np.ndarray | None = None
    flipped_left: bool = False
    flipped_right: bool = False
    reprojection_px: float = float("nan")
    max_distance_error_mm: float = float("nan")
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.left_px is not None


@dataclass
class RejectionCounter:
    """Frames accepted, and frames rejected per reason."""

    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=dict)

    def add(self, result: LabelResult | StereoLabel | str | None) -> None:
        """Count one frame: a result (by its ``reason``), a reason, or None for accepted."""
        reason = result if result is None or isinstance(result, str) else result.reason
        if reason is None:
            self.accepted += 1
        else:
            self.rejected[reason] = self.rejected.get(reason, 0) + 1

    def update(self, results: Iterable[LabelResult | StereoLabel | str | None]) -> None:
        for r in results:
            self.add(r)

    def merge(self, other: RejectionCounter) -> None:
        self.accepted += other.accepted
        for k, v in other.rejected.items():
            self.rejected[k] = self.rejected.get(k, 0) + v

    @property
    def total(self) -> int:
        return self.accepted + sum(self.rejected.values())

    def as_dict(self) -> dict[str, int]:
        """Reason -> count, most frequent first (what ``WandObservations.rejected`` holds)."""
        return dict(sorted(self.rejected.items(), key=lambda kv: (-kv[1], kv[0])))


# ---- one view -------------------------------------------------------------------------------


def _unit_rays(xy: np.ndarray) -> np.ndarray:
    u = np.column_stack([xy, np.ones(len(xy))])
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _wand_depths(rays: np.ndarray, wand: WandSpec) -> np.ndarray | None:
    """Distances (3,) along unit ``rays`` (first, middle, last) at which three points with the
    wand's spacing are collinear; None if no solution lies in front of the camera.

    ``X_mid = (1 - t) X_first + t X_last`` with ``t = (p1 - p0) / (p2 - p0)`` is three linear
    equations in the three distances; the null vector fixes their ratios, the wand's length their
    scale.
    """
    p0, p1, p2 = wand.sphere_positions_mm
    t = (p1 - p0) / (p2 - p0)
    M = np.column_stack([(1 - t) * rays[0], -rays[1], t * rays[2]])
    lam = np.linalg.svd(M)[2][-1]
    if lam[0] < 0:
        lam = -lam
    if (lam <= 0).any():
        return None
    length = float(np.linalg.norm(lam[2] * rays[2] - lam[0] * rays[0]))
    if length <= 0:
        return None
    return lam * ((p2 - p0) / 1000.0 / length)


def refit_without_rod(
    detector: SphereDetector, image_bgr: np.ndarray, label: LabelResult
) -> LabelResult:
    """Fit the labelled spheres again with the outline along the wand's axis left out.

    Labelling tells where the rod is: it runs through all three spheres along the line from
    the first to the last. A sphere whose refit fails keeps its first fit.
    """
    if label.points_px is None or len(label.blobs) != 3:
        return label
    axis = label.points_px[2] - label.points_px[0]
    if float(np.linalg.norm(axis)) < 1e-6:
        return label
    blobs, points = [], label.points_px.copy()
    for k, blob in enumerate(label.blobs):
        again = detector.refine(
            image_bgr, blob.ellipse_centre_px, blob.radius_px, exclude_axis_px=axis
        )
        if again is None:
            blobs.append(blob)
            continue
        blobs.append(again)
        points[k] = again.centre_px
    return LabelResult(
        points_px=points,
        blobs=tuple(blobs),
        reason=label.reason,
        cost=label.cost,
        depths_m=label.depths_m,
    )


def label_wand(
    blobs: Sequence[SphereBlob], wand: WandSpec, config: LabelConfig | None = None
) -> LabelResult:
    """Pick the three blobs that are the wand and order them first, middle, last.

    Rejections: ``FEWER_THAN_3``; ``NOT_COLLINEAR`` (no three blobs on a line, one between the
    others); ``RATIO_MISMATCH`` (lines, but none with the wand's spacing); ``AMBIGUOUS`` (two
    labellings fit about equally well).
    """
    cfg = config or LabelConfig()
    cand = sorted(blobs, key=lambda b: -b.score)[: cfg.max_blobs]
    if len(cand) < 3:
        return LabelResult.rejected(FEWER_THAN_3)
    xy = np.array([b.centre_normalized for b in cand], dtype=np.float64)
    if not np.isfinite(xy).all():
        raise ValueError("label_wand needs blobs with centre_normalized (from SphereDetector)")
    focal = float(np.nanmean([b.focal_px for b in cand]))
    dist = np.array([b.distance_m for b in cand], dtype=np.float64)
    rays = _unit_rays(xy)
    p0, p1, p2 = wand.sphere_positions_mm
    ratio_expected = (p1 - p0) / (p2 - p1)
    any_collinear = False
    # (cost, order of indices first/middle/last, depths)
    found: list[tuple[float, tuple[int, int, int], np.ndarray | None]] = []
    for trio in itertools.combinations(range(len(cand)), 3):
        picked = _middle_between(xy, trio)
        if picked is None:
            continue
        a, m, c = picked
        off_line_px = focal * _line_distance(xy[a], xy[c], xy[m])
        if off_line_px > cfg.collinear_tol_px:
            continue
        any_collinear = True
        line_cost = (off_line_px / cfg.collinear_tol_px) ** 2
        for order in ((a, m, c), (c, m, a)):
            seg0 = float(np.linalg.norm(xy[order[1]] - xy[order[0]]))
            seg1 = float(np.linalg.norm(xy[order[2]] - xy[order[1]]))
            depths = _wand_depths(rays[list(order)], wand)
            dist_o = dist[list(order)]
            if np.isfinite(dist_o).all():
                if depths is None:
                    continue
                err = float(np.max(np.abs(depths / dist_o - 1.0)))
                if err > cfg.distance_tol:
                    continue
                cost = line_cost + (err / cfg.distance_tol) ** 2
            else:
                ratio = seg0 / (seg1 + 1e-12)
                rel = abs(ratio / ratio_expected - 1.0)
                if rel > cfg.ratio_tol:
                    continue
                cost = line_cost + (rel / cfg.ratio_tol) ** 2
            found.append((cost, order, depths))
    if not found:
        return LabelResult.rejected(RATIO_MISMATCH if any_collinear else NOT_COLLINEAR)
    found.sort(key=lambda f: f[0])
    best = found[0]
    if len(found) > 1 and found[1][0] - best[0] < cfg.ambiguity_margin:
        return LabelResult.rejected(AMBIGUOUS)
    order = best[1]
    chosen = tuple(cand[i] for i in order)
    return LabelResult(
        points_px=np.array([b.centre_px for b in chosen], dtype=np.float64),
        blobs=chosen,
        cost=best[0],
        depths_m=best[2],
    )


def _middle_between(xy: np.ndarray, trio: tuple[int, int, int]) -> tuple[int, int, int] | None:
    """(end, middle, end) if one of the three lies strictly between the other two."""
    for m in trio:
        a, c = (i for i in trio if i != m)
        d = xy[c] - xy[a]
        n2 = float(d @ d)
        if n2 <= 0:
            return None
        t = float((xy[m] - xy[a]) @ d) / n2
        if 0.05 < t < 0.95:
            return a, m, c
    return None


def _line_distance(a: np.ndarray, c: np.ndarray, m: np.ndarray) -> float:
    d = c - a
    return abs(float(d[0] * (m[1] - a[1]) - d[1] * (m[0] - a[0]))) / float(np.linalg.norm(d))


# ---- stereo ---------------------------------------------------------------------------------


def label_stereo(
    left: LabelResult,
    right: LabelResult,
    stereo: StereoCalibration,
    wand: WandSpec,
    config: StereoConfig | None = None,
) -> StereoLabel:
    """Check a ZED's two labellings against each other and against the wand, metrically."""
    cfg = config or StereoConfig()
    if left.points_px is None or right.points_px is None:
        return StereoLabel(reason=NOT_IN_BOTH_VIEWS)
    xl = undistort_to_normalized(left.points_px, stereo.left)
    xr = undistort_to_normalized(right.points_px, stereo.right)
    f_l = 0.5 * (stereo.left.fx_px + stereo.left.fy_px)
    f_r = 0.5 * (stereo.right.fx_px + stereo.right.fy_px)
    P_l = np.hstack([np.eye(3), np.zeros((3, 1))])
    P_r = np.hstack([stereo.R_right_from_left, stereo.T_right_from_left_m.reshape(3, 1)])
    want = np.asarray(wand.distances_mm, dtype=np.float64)
    base_tol = np.maximum(cfg.distance_tol_mm, cfg.distance_tol_frac * want)
    depth_per_disp = 1.0 / (f_l * max(stereo.baseline_m, 1e-6))  # dZ = Z^2 * this * d(disp)
    passing: list[tuple[float, StereoLabel]] = []
    any_consistent = False
    for flip_l, flip_r in itertools.product((False, True), repeat=2):
        a = xl[::-1] if flip_l else xl
        b = xr[::-1] if flip_r else xr
        X = cv2.triangulatePoints(P_l, P_r, a.T.copy(), b.T.copy())
        X = (X[:3] / X[3]).T  # (3, 3) in the left frame
        Xr = X @ stereo.R_right_from_left.T + stereo.T_right_from_left_m
        if (X[:, 2] <= 0).any() or (Xr[:, 2] <= 0).any():
            continue
        reproj = max(
            float(np.max(f_l * np.linalg.norm(X[:, :2] / X[:, 2:] - a, axis=1))),
            float(np.max(f_r * np.linalg.norm(Xr[:, :2] / Xr[:, 2:] - b, axis=1))),
        )
        if reproj > cfg.max_reprojection_px:
            continue
        any_consistent = True
        d = 1000.0 * np.array(
            [
                np.linalg.norm(X[1] - X[0]),
                np.linalg.norm(X[2] - X[1]),
                np.linalg.norm(X[2] - X[0]),
            ]
        )
        err = np.abs(d - want)
        tol = base_tol + cfg.n_sigma * 1000.0 * _distance_sigma_m(
            X, depth_per_disp * cfg.disparity_sigma_px
        )
        if (err > tol).any():
            continue
        lp = left.points_px[::-1] if flip_l else left.points_px
        rp = right.points_px[::-1] if flip_r else right.points_px
        label = StereoLabel(
            left_px=lp.copy(),
            right_px=rp.copy(),
            points_left_m=X,
            distances_mm=d,
            flipped_left=flip_l,
            flipped_right=flip_r,
            reprojection_px=reproj,
            max_distance_error_mm=float(err.max()),
        )
        passing.append((float(np.max(err / tol)), label))
    if not passing:
        return StereoLabel(reason=WAND_MISMATCH if any_consistent else VIEWS_DISAGREE)
    if len(passing) > 1:
        return StereoLabel(reason=AMBIGUOUS)
    return passing[0][1]


def _distance_sigma_m(X: np.ndarray, depth_sigma_per_z2: float) -> np.ndarray:
    """(3,) standard deviation of the distances (0-1, 1-2, 0-2) between triangulated points
    (3, 3) when each depth errs by ``Z^2 * depth_sigma_per_z2`` along its own ray."""
    out = np.empty(3)
    for k, (i, j) in enumerate(((0, 1), (1, 2), (0, 2))):
        e = X[j] - X[i]
        e = e / max(float(np.linalg.norm(e)), 1e-12)
        # moving point i by dZ along its ray moves it by X_i / Z_i * dZ
        gi = float(e @ X[i]) / X[i, 2] * X[i, 2] ** 2 * depth_sigma_per_z2
        gj = float(e @ X[j]) / X[j, 2] * X[j, 2] ** 2 * depth_sigma_per_z2
        out[k] = math.hypot(gi, gj)
    return out
