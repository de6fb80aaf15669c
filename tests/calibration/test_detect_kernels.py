"""The wand detector's numba kernels against their slow, obvious numpy twins.

Each fast kernel in ``calibration.detect.kernels`` has a reference (the numpy code it replaced,
in ``calibration.detect._reference``, or numpy/cv2 itself) that ``DetectorConfig(kernels="numpy")``
runs; here each pair is fed the same synthetic inputs (anti-aliased discs of the spheres' colour
over a textured room, a lens with distortion, outliers like the wand's rod) and must agree within
the stated tolerances. The detector on simulator frames, both ways, is compared in
tests/calibration/test_detect.py.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from calibration.detect import _reference as reference
from calibration.detect import kernels as K
from calibration.detect.config import DetectorConfig, colour_mask
from calibration.detect.detector import SphereDetector
from calibration.detect.sphere_geometry import project_directions
from protocol.camera import Intrinsics

SPHERE_BGR = (20, 105, 235)  # about the simulator's orange, lit


def _lens() -> Intrinsics:
    base = Intrinsics.from_fov(1920, 1200, 110.0)
    return Intrinsics(
        width_px=base.width_px,
        height_px=base.height_px,
        fx_px=base.fx_px,
        fy_px=base.fy_px * 1.001,
        cx_px=base.cx_px + 3.0,
        cy_px=base.cy_px - 2.0,
        dist=(-0.05, 0.01, 0.0005, -0.0003, -0.001),
    )


def _room(h: int, w: int, seed: int) -> np.ndarray:
    """A textured, mostly dull background (smooth blotches plus a few hard edges)."""
    rng = np.random.default_rng(seed)
    grey = rng.integers(50, 180, (h // 8 + 2, w // 8 + 2, 1))
    tint = rng.integers(-25, 25, (h // 8 + 2, w // 8 + 2, 3))
    small = np.clip(grey + tint, 0, 255).astype(np.uint8)
    room = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(4):
        x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
        colour = tuple(int(v) for v in rng.integers(0, 255, 3))
        cv2.rectangle(room, (x0, y0), (x0 + w // 3, y0 + 3), colour, -1)
    return room


def _disc(img: np.ndarray, centre: tuple[float, float], radius: float, bgr=SPHERE_BGR) -> None:
    """An anti-aliased disc drawn in place (1/16 px precision)."""
    cv2.circle(
        img,
        (round(centre[0] * 16), round(centre[1] * 16)),
        round(radius * 16),
        tuple(float(v) for v in bgr),
        -1,
        cv2.LINE_AA,
        shift=4,
    )


# ---- small numeric helpers ---------------------------------------------------------------------


def test_bilinear_kernel_matches_numpy():
    rng = np.random.default_rng(1)
    img = rng.random((23, 31, 4)).astype(np.float32)
    pts = np.column_stack([rng.uniform(-2, 33, 500), rng.uniform(-2, 25, 500)])
    pts[:5] = np.array([[0, 0], [30, 22], [29.9999, 21.9999], [15, 11], [-0.0, 22]])  # corners
    fast, inside_fast = K._bilinear_nb(img, pts)
    slow, inside_slow = reference.bilinear(img, pts)
    assert (inside_fast == inside_slow).all()
    # the reference interpolates in float32
    assert np.abs(fast - slow).max() < 2e-6


def test_least_squares_median_and_null_vector_helpers_match_numpy():
    rng = np.random.default_rng(2)
    for n in (6, 7, 40, 128):
        M = rng.normal(size=(n, 3)) * [0.01, 0.01, 1.0] + [0.3, -0.2, 0.0]
        b = rng.normal(size=n)
        ref = np.linalg.lstsq(M, b, rcond=None)[0]
        assert np.allclose(K._lstsq_nb(M, b), ref, rtol=1e-9, atol=1e-12)
        v = rng.normal(size=n)
        assert K._median_nb(v) == np.median(v)  # the same value, odd or even n
        M6 = rng.normal(size=(n, 6))
        M6[:, 5] = M6[:, :5] @ rng.normal(size=5) + 1e-3 * rng.normal(size=n)  # nearly singular
        ref6 = np.linalg.svd(M6, full_matrices=False)[2][-1]
        got = K._smallest_right_singular_vector_nb(M6)
        assert abs(abs(float(got @ ref6)) - 1.0) < 1e-10


# ---- per-sphere kernels ------------------------------------------------------------------------


def _sphere_roi(seed: int, radius: float, bright: float = 1.0):
    """(roi, background roi, centre guess, A guess) for one synthetic sphere; ``bright`` > 1
    saturates the red channel at the disc's edge (a sphere lit hard by a lamp)."""
    rng = np.random.default_rng(seed)
    size = int(2 * radius + 16)
    bg = _room(size, size, seed)
    roi = bg.copy()
    centre = (size / 2 + rng.uniform(-0.5, 0.5), size / 2 + rng.uniform(-0.5, 0.5))
    colour = np.clip(np.array(SPHERE_BGR) * bright, 0, 255)
    _disc(roi, centre, radius, colour)
    noisy = np.clip(roi + rng.normal(0, 1.5, roi.shape), 0, 255).astype(np.uint8)
    guess = np.array(centre) + rng.uniform(-0.4, 0.4, 2)
    A = np.array([[1.08, 0.03], [0.03, 0.93]]) / radius**2
    return noisy, bg, guess, A


@pytest.mark.parametrize("bright", [1.0, 1.3])
@pytest.mark.parametrize("with_background", [True, False])
def test_edge_points_kernel_matches_reference(bright, with_background):
    det = SphereDetector(_lens(), 0.02)
    counts = []
    for seed in range(12):
        roi, bg, c, A = _sphere_roi(seed, radius=3.0 + seed, bright=bright)
        bg_roi = bg if with_background else None
        for density in (1.0, 2.0):
            fast, n_fast = det._edge_points(roi, bg_roi, c, A, density)
            slow, n_slow = reference.edge_points(roi, bg_roi, c, A, density, det.config)
            assert n_fast == n_slow
            assert fast.shape == slow.shape, f"seed {seed}: {len(fast)} vs {len(slow)} edges"
            if len(fast):
                assert np.abs(fast - slow).max() < 1e-4  # px; float32 in the reference
            counts.append(len(fast) / n_fast)
    assert np.mean(counts) > 0.5  # the comparison saw real edges


def test_robust_cone_kernel_matches_reference():
    """Exact silhouettes through a distorted lens, with noise and with a run of points pushed
    outwards (the rod), fitted both ways."""
    lens = _lens()
    det = SphereDetector(lens, 0.02)
    rng = np.random.default_rng(3)
    for trial in range(20):
        theta = math.radians(rng.uniform(0, 50))
        phi = rng.uniform(0, 2 * math.pi)
        D_m = rng.uniform(0.8, 4.0)
        a = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi)])
        a = np.append(a, math.cos(theta))
        alpha = math.asin(0.02 / D_m)
        e1 = np.cross(a, [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        n = int(rng.integers(12, 100))
        ang = np.linspace(0, 2 * math.pi, n, endpoint=False)
        rays = math.cos(alpha) * a + math.sin(alpha) * (
            np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2
        )
        edges = project_directions(rays, lens) + rng.normal(0, 0.03, (n, 2))
        if trial % 2:
            centre = edges.mean(axis=0)
            k = n // 6
            edges[:k] += (
                0.8 * (edges[:k] - centre) / np.linalg.norm(edges[:k] - centre, axis=1)[:, None]
            )
        fast = det._robust_fit(edges)
        slow = reference.robust_fit(edges, det.intrinsics, det.config)
        assert fast is not None and slow is not None
        assert (fast.keep == slow.keep).all()
        assert np.abs(fast.axis - slow.axis).max() < 1e-12
        assert fast.sin_alpha == pytest.approx(slow.sin_alpha, rel=1e-10)
        assert np.abs(fast.residuals_px - slow.residuals_px).max() < 1e-8
        assert np.abs(fast.rays - slow.rays).max() < 1e-15
    # too few points, or all outliers: both give up
    assert (
        det._robust_fit(edges[:5]) is None
        and reference.robust_fit(edges[:5], det.intrinsics, det.config) is None
    )


def test_ellipse_through_kernel_matches_numpy():
    det = SphereDetector(_lens(), 0.02)
    rng = np.random.default_rng(4)
    for _ in range(30):
        c = rng.uniform(5, 40, 2)
        r1, r2 = rng.uniform(2.5, 20), rng.uniform(2.5, 20)
        t = rng.uniform(0, math.pi)
        # 6 or more: with 5, fit_conic's reduced SVD has no null vector to return (the kernel
        # finds the exact conic); refine never fits fewer than 8
        n = int(rng.integers(6, 120))
        ang = rng.uniform(0, 2 * math.pi, n)
        R = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        pts = c + (np.column_stack([r1 * np.cos(ang), r2 * np.sin(ang)]) @ R.T)
        pts += rng.normal(0, 0.05, pts.shape)
        fast = det._ellipse_through(pts)
        slow = reference.ellipse_through(pts)
        assert (fast is None) == (slow is None)
        if fast is None or slow is None:
            continue
        assert np.abs(fast[0] - slow[0]).max() < 1e-9  # centre, px
        assert np.abs(fast[1] - slow[1]).max() < 1e-9 * np.abs(slow[1]).max()
    line = np.column_stack([np.arange(8.0), 2 * np.arange(8.0)])
    assert det._ellipse_through(line) is None and reference.ellipse_through(line) is None
    assert det._ellipse_through(line[:4]) is None


# ---- candidates --------------------------------------------------------------------------------


def test_colour_table_is_exactly_cv2s_colour_test():
    det = SphereDetector(_lens(), 0.02)
    rng = np.random.default_rng(5)
    colours = rng.integers(0, 256, (200_000, 1, 3), dtype=np.uint8)
    colours[:4096, 0] = np.array(SPHERE_BGR) + rng.integers(-40, 40, (4096, 3))  # near orange
    table = K.colour_table(det.config.hsv_bounds())
    idx = (colours[:, 0, 0].astype(np.int64) << 16) | (colours[:, 0, 1].astype(np.int64) << 8)
    idx |= colours[:, 0, 2]
    looked_up = (table[idx >> 3] >> (idx & 7)) & 1
    assert (looked_up == colour_mask(colours, det.config)[:, 0]).all()
    assert looked_up.sum() > 1000


def test_candidate_mask_kernel_matches_cv2():
    h, w = 240, 320
    bg = _room(h, w, 6)
    det = SphereDetector(Intrinsics.from_fov(w, h, 90.0), 0.02)
    det.set_background(bg)
    rng = np.random.default_rng(6)
    frame = bg.copy()
    for _ in range(15):
        _disc(frame, tuple(rng.uniform(0, [w, h])), rng.uniform(1, 12))
    frame[100:140, 10:60] = SPHERE_BGR  # static-looking clutter, also in the background
    bg[100:140, 10:60] = SPHERE_BGR
    det.set_background(bg)
    frame = np.clip(frame + rng.normal(0, 3, frame.shape), 0, 255).astype(np.uint8)
    fast = det._candidate_mask(frame)
    slow = reference.candidate_mask(det._downsample(frame), det._background, det.config)
    assert fast.dtype == slow.dtype == np.uint8
    assert (fast == slow).all() and fast.sum() > 100
    assert len(det.candidates(frame)) >= 5
    # without a background the cv2 path runs as it is
    det.clear_background()
    slow = reference.candidate_mask(det._downsample(frame), None, det.config)
    assert (det._candidate_mask(frame) == slow).all()


# ---- the detector, both ways -------------------------------------------------------------------


@pytest.mark.parametrize("centre_method", ["sphere", "conic"])
def test_detector_gives_the_same_spheres_with_either_kernels(centre_method):
    """A synthetic frame of discs (a pinhole: discs are the spheres' images near the axis)."""
    intr = Intrinsics.from_fov(640, 400, 60.0)
    bg = _room(400, 640, 7)
    frame = bg.copy()
    for x, r in ((150, 4.0), (300, 6.0), (480, 8.5)):
        _disc(frame, (x + 0.3, 200.6), r)
    fast = SphereDetector(intr, 0.02, DetectorConfig(centre_method=centre_method))
    slow = SphereDetector(intr, 0.02, DetectorConfig(centre_method=centre_method, kernels="numpy"))
    for det in (fast, slow):
        det.set_background(bg)
    a, b = fast.detect(frame), slow.detect(frame)
    assert len(a) == len(b) == 3
    for p, q in zip(a, b, strict=True):
        assert np.abs(np.subtract(p.centre_px, q.centre_px)).max() < 1e-5
        assert p.n_edge_points == q.n_edge_points
        assert p.distance_m == pytest.approx(q.distance_m, rel=1e-6)


def test_kernels_config_is_checked():
    with pytest.raises(ValueError, match="kernels"):
        DetectorConfig(kernels="cuda")
