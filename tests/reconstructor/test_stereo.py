"""Stereo depth against the simulator's ground truth: the accuracy a user can rely on, the
rectification maths on its own, the plug-in seam for learned matchers, and clear errors."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol.camera import Camera, Intrinsics, Pose, undistort_to_normalized
from protocol.errors import UserError
from reconstructor.depth.matcher import StereoMatcher
from reconstructor.depth.matchers import ENTRY_POINT_GROUP, load_matcher
from reconstructor.depth.sgbm import SgbmWlsMatcher, lr_consistent, zncc_at_disparity
from reconstructor.depth.stereo import DepthMap, StereoRectifier, compute_depth, rectifier
from reconstructor.depth.stereo_config import StereoConfig
from reconstructor.errors import (
    MatcherNotFoundError,
    MatcherWeightsError,
    ReconstructConfigError,
    StereoError,
)

UNIT = 1
T_S = 1.0
# Surfaces with texture a matcher can lock on to; the sim's walls and ceiling are blank paint.
TEXTURED = ("floor", "scrubs", "skin", "cap", "mask", "shoes", "tray", "steel", "rubber")


# ---- a plug-in matcher, registered without an entry point ---------------------------------
class ConstantMatcher(StereoMatcher):
    """Every pixel at one disparity: enough to check the seam end to end."""

    name = "constant"
    disparity_px = 12.5

    def __init__(self, weights_path: Path | None = None) -> None:
        self.weights_path = weights_path

    def match(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        return np.full(left_rgb.shape[:2], self.disparity_px, np.float32)


class WeightlessMatcher(ConstantMatcher):
    needs_weights = False


def not_a_matcher(weights_path=None):
    return object()


# ---- fixtures ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def svga(world):
    left, right = world.render_stereo(UNIT, T_S, "SVGA")
    stereo = world.unit(UNIT).factory.stereo("SVGA")
    depth = compute_depth(
        left.image_rgb, right.image_rgb, stereo.left, stereo.right, stereo.right_from_left
    )
    names = [o.name for o in world.scene_at(T_S).objects]
    return left, stereo, depth, names


def _bilinear_truth(depth: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Truth z at sub-pixel positions; NaN off the image and across depth edges (where the
    four neighbours differ by more than 1 %), so edges do not count as matching errors."""
    h, w = depth.shape
    x, y = px[:, 0], px[:, 1]
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    fx, fy = x - x0, y - y0
    n = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]])
    with np.errstate(invalid="ignore"):
        smooth = inside & np.isfinite(n).all(0) & (n.max(0) - n.min(0) < 0.01 * n.min(0))
    z = n[0] * (1 - fx) * (1 - fy) + n[1] * fx * (1 - fy) + n[2] * (1 - fx) * fy + n[3] * fx * fy
    return np.where(smooth, z, np.nan)


def _relative_errors(depth: DepthMap, sensor: Intrinsics, truth_depth: np.ndarray):
    """Each valid pixel's 3D point, projected into the ORIGINAL (distorted) left sensor image,
    against the sim's true z along the same ray: (relative error, true z) where truth exists."""
    points, _ = depth.points_in_left_camera()
    cam = Camera(name="left", intrinsics=sensor, pose=Pose(R=np.eye(3)))
    px, z = cam.project(points.astype(np.float64))
    z_true = _bilinear_truth(truth_depth, px)
    ok = np.isfinite(z_true)
    return np.abs(z[ok] - z_true[ok]) / z_true[ok], z_true[ok]


def _labels_in_rectified(rect: StereoRectifier, object_index: np.ndarray) -> np.ndarray:
    mx, my = rect.map_left
    labels = cv2.remap(object_index.astype(np.float32), mx, my, cv2.INTER_NEAREST)
    if rect.match_size != rect.full_size:
        labels = cv2.resize(labels, rect.match_size, interpolation=cv2.INTER_NEAREST)
    return labels.astype(int)


# ---- rectification: calibration maths only ------------------------------------------------
def test_rectified_rows_agree_and_maps_invert_the_projection(world):
    """A 3D point lands on the same row in both rectified images, and the rectified disparity
    gives back its depth; the cached maps send each rectified pixel to where the point really
    is in the distorted sensor image. No matching involved."""
    st = world.unit(0).factory.stereo("HD1200")  # distorted lenses: rational left, k3 != 0 right
    assert st.left.is_rational and not st.right.is_rational
    rect = StereoRectifier(st.left, st.right, st.right_from_left)
    rng = np.random.default_rng(0)
    n = 400
    ray = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n), np.ones(n)])
    pts_left = ray * rng.uniform(0.5, 8.0, n)[:, None]
    left_cam = Camera(name="l", intrinsics=st.left, pose=Pose(R=np.eye(3)))
    right_cam = Camera(name="r", intrinsics=st.right, pose=st.right_from_left)
    px_l, _ = left_cam.project(pts_left)
    px_r, _ = right_cam.project(pts_left)

    def to_rectified(px, intr, R, P):
        n_xy = undistort_to_normalized(px, intr)
        r = np.column_stack([n_xy, np.ones(len(n_xy))]) @ R.T
        return r[:, :2] / r[:, 2:] * np.diag(P)[:2] + P[:2, 2]

    uv_l = to_rectified(px_l, st.left, rect.rect_from_left, rect.P_left)
    uv_r = to_rectified(px_r, st.right, rect.rect_from_right, rect.P_right)
    assert np.abs(uv_l[:, 1] - uv_r[:, 1]).max() < 0.05

    z_rect = (pts_left @ rect.rect_from_left.T)[:, 2]
    disparity = uv_l[:, 0] - uv_r[:, 0]
    np.testing.assert_allclose(rect.P_left[0, 0] * rect.baseline_m / disparity, z_rect, rtol=1e-6)
    assert rect.baseline_m == pytest.approx(st.baseline_m, rel=1e-3)

    h, w = st.left.height_px, st.left.width_px
    inside = (uv_l[:, 0] > 1) & (uv_l[:, 0] < w - 2) & (uv_l[:, 1] > 1) & (uv_l[:, 1] < h - 2)
    mx, my = rect.map_left
    samp = uv_l[inside].astype(np.float32)
    back_x = cv2.remap(mx, samp[:, 0], samp[:, 1], cv2.INTER_LINEAR).ravel()
    back_y = cv2.remap(my, samp[:, 0], samp[:, 1], cv2.INTER_LINEAR).ravel()
    # bilinear interpolation of the maps themselves costs a little: 0.05 px is far below SGBM's
    assert np.abs(back_x - px_l[inside, 0]).max() < 0.05
    assert np.abs(back_y - px_l[inside, 1]).max() < 0.05


# ---- accuracy on the sim -----------------------------------------------------------------
def test_svga_depth_is_accurate_where_it_is_valid(svga):
    """The bar a user relies on, SVGA, noisy sensor images, SGBM + WLS with all checks.

    Measured (seed 11, t = 1 s, 4 units): median |error| 0.8-1.0 % of depth at 1-4 m, 3-7 % of
    valid pixels off by more than 5 % (depth edges the 1 % smoothness test lets through, the
    grazing ceiling). The bars leave room for noise without hiding a regression such as a
    half-pixel rectification error (which doubles the median at 4 m).
    """
    left, stereo, depth, _ = svga
    rel, z_true = _relative_errors(depth, stereo.left, left.depth_m)
    near = (z_true >= 1.0) & (z_true <= 4.0)
    assert near.sum() > 50_000
    assert np.median(rel[near]) < 0.015
    assert np.mean(rel > 0.05) < 0.10
    assert depth.depth_m.dtype == np.float32
    assert np.isnan(depth.depth_m[~depth.valid]).all()
    assert (depth.depth_m[depth.valid] >= 0.4).all() and (depth.depth_m[depth.valid] <= 8).all()


def test_svga_depth_through_the_rational_lens_is_as_accurate(world):
    """The sim's unit 0 has a left sensor on the 8-term rational model (k4..k6): rectification
    and depth through it meet the same bars, against the same truth."""
    left, right = world.render_stereo(0, T_S, "SVGA")
    stereo = world.unit(0).factory.stereo("SVGA")
    assert stereo.left.is_rational
    depth = compute_depth(
        left.image_rgb, right.image_rgb, stereo.left, stereo.right, stereo.right_from_left
    )
    rel, z_true = _relative_errors(depth, stereo.left, left.depth_m)
    near = (z_true >= 1.0) & (z_true <= 4.0)
    assert near.sum() > 50_000
    assert np.median(rel[near]) < 0.015
    assert np.mean(rel > 0.05) < 0.10


def test_svga_depth_covers_textured_surfaces_and_rejects_blank_walls(svga, world):
    """>= 85 % of textured pixels (floor, people, instruments) get a depth (measured 87 % with
    the retuned ZNCC 0.3, 83 % with the old 0.5); blank walls almost none (under 10 %), instead
    of a smooth sheet at the wrong depth."""
    left, stereo, depth, names = svga
    rect = rectifier(stereo.left, stereo.right, stereo.right_from_left)
    labels = _labels_in_rectified(rect, left.object_index)
    kind = np.array([n.split(":")[-1] for n in names] + ["?"])
    kinds = kind[np.clip(labels, -1, len(names))]
    textured = np.isin(kinds, TEXTURED)
    walls = kinds == "walls"
    assert textured.sum() > 50_000 and walls.sum() > 50_000
    assert depth.valid[textured].mean() >= 0.85
    assert depth.valid[walls].mean() < 0.10


def test_hd1200_matches_at_half_size_and_keeps_accuracy(world):
    """HD1200 defaults to match_scale 0.5: a 960x600 depth map as accurate as SVGA's."""
    left, right = world.render_stereo(UNIT, T_S, "HD1200")
    st = world.unit(UNIT).factory.stereo("HD1200")
    config = StereoConfig.for_resolution(st.left.width_px)
    assert config.match_scale == 0.5
    depth = compute_depth(
        left.image_rgb, right.image_rgb, st.left, st.right, st.right_from_left, config
    )
    assert depth.depth_m.shape == (600, 960)
    assert depth.intrinsics.width_px == 960
    rel, z_true = _relative_errors(depth, st.left, left.depth_m)
    near = (z_true >= 1.0) & (z_true <= 4.0)
    assert np.median(rel[near]) < 0.015
    assert np.mean(rel > 0.05) < 0.10


def test_points_in_world_follow_the_left_pose(svga, world):
    _, _, depth, _ = svga
    pose = world.unit(UNIT).left_pose
    cam_pts, colours = depth.points_in_left_camera()
    world_pts, colours_w = depth.points_in_world(pose)
    np.testing.assert_allclose(pose.transform(world_pts), cam_pts, atol=2e-5)
    assert np.array_equal(colours, colours_w)
    assert colours.dtype == np.float32 and 0 <= colours.min() and colours.max() <= 1


# ---- the matcher's pieces against slow twins ----------------------------------------------
def test_lr_check_matches_a_loop():
    rng = np.random.default_rng(1)
    dl = rng.uniform(0, 8, (6, 20)).astype(np.float32)
    dr = (dl + rng.choice([0.0, 0.5, 3.0], dl.shape)).astype(np.float32)
    dl[0, 3] = np.nan
    fast = lr_consistent(dl, dr, 1.0)
    slow = np.zeros_like(fast)
    for y in range(dl.shape[0]):
        for x in range(dl.shape[1]):
            d = dl[y, x]
            if not np.isfinite(d) or d <= 0:
                continue
            xr = int(np.rint(x - d))
            if 0 <= xr < dl.shape[1] and dr[y, xr] > 0:
                slow[y, x] = abs(d - dr[y, xr]) <= 1.0
    assert np.array_equal(fast, slow)


def test_zncc_matches_a_loop():
    from reconstructor.depth.sgbm import _highpass

    rng = np.random.default_rng(2)
    left = rng.uniform(0, 255, (30, 40)).astype(np.float32)
    right = np.roll(left, -3, axis=1) + rng.normal(0, 20, left.shape).astype(np.float32)
    disp = np.full(left.shape, 3.0, np.float32)
    fast = zncc_at_disparity(left, right, disp, 5)
    a = _highpass(left)
    b = _highpass(np.roll(right, 3, axis=1))  # the right image sampled at x - 3
    for y, x in [(10, 10), (15, 20), (20, 30)]:
        pa = a[y - 2 : y + 3, x - 2 : x + 3].ravel() - a[y - 2 : y + 3, x - 2 : x + 3].mean()
        pb = b[y - 2 : y + 3, x - 2 : x + 3].ravel() - b[y - 2 : y + 3, x - 2 : x + 3].mean()
        slow = (pa @ pb) / np.sqrt((pa @ pa) * (pb @ pb))
        assert fast[y, x] == pytest.approx(slow, abs=1e-4)
    assert 0.3 < np.median(fast[5:-5, 5:-5]) < 1.0


# ---- the plug-in seam --------------------------------------------------------------------
def test_a_plugin_matcher_runs_through_compute_depth(svga, tmp_path):
    left, stereo, _, _ = svga
    weights = tmp_path / "weights.pth"
    weights.write_bytes(b"not really weights")
    matcher = load_matcher(f"{__name__}:ConstantMatcher", weights)
    assert isinstance(matcher, ConstantMatcher) and matcher.weights_path == weights
    right = left.image_rgb  # the constant matcher ignores the images
    depth = compute_depth(
        left.image_rgb, right, stereo.left, stereo.right, stereo.right_from_left, matcher=matcher
    )
    fb = depth.intrinsics.fx_px * depth.baseline_m
    np.testing.assert_allclose(depth.depth_m[depth.valid], fb / 12.5, rtol=1e-6)
    assert depth.valid_fraction > 0.8  # all but the strip whose partner is off the right image


def test_load_matcher_finds_entry_points_and_the_default(monkeypatch, tmp_path):
    assert isinstance(load_matcher("sgbm"), SgbmWlsMatcher)
    fake = importlib.metadata.EntryPoint(
        name="fake_stereo", value=f"{__name__}:WeightlessMatcher", group=ENTRY_POINT_GROUP
    )
    real = importlib.metadata.entry_points

    def entry_points(**kwargs):
        return [fake] if kwargs.get("group") == ENTRY_POINT_GROUP else real(**kwargs)

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    assert isinstance(load_matcher("fake_stereo"), WeightlessMatcher)  # needs no weights


def test_missing_matcher_or_weights_say_what_to_do(tmp_path):
    with pytest.raises(MatcherNotFoundError) as exc:
        load_matcher("foundation_stereo", tmp_path / "w.pth")
    msg = str(exc.value)
    assert "foundation_stereo" in msg and ENTRY_POINT_GROUP in msg and "sgbm" in msg
    assert isinstance(exc.value, UserError) and isinstance(exc.value, LookupError)

    with pytest.raises(MatcherWeightsError, match=r"ConstantMatcher.*needs a local weights path"):
        load_matcher(f"{__name__}:ConstantMatcher", None)
    with pytest.raises(MatcherWeightsError, match="does not exist"):
        load_matcher(f"{__name__}:ConstantMatcher", tmp_path / "missing.pth")
    with pytest.raises(MatcherNotFoundError, match="cannot be imported"):
        load_matcher("no_such_module_xyz:Matcher", None)
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"")
    with pytest.raises(MatcherNotFoundError, match="not a StereoMatcher"):
        load_matcher(f"{__name__}:not_a_matcher", weights)


# ---- bad input ---------------------------------------------------------------------------
def _svga_pair(stereo):
    h, w = stereo.left.height_px, stereo.left.width_px
    return np.zeros((h, w, 3), np.uint8), np.zeros((h, w, 3), np.uint8)


def test_bad_images_are_refused_with_the_problem_named(world):
    st = world.unit(0).factory.stereo("SVGA")
    left, right = _svga_pair(st)
    args = (st.left, st.right, st.right_from_left)
    with pytest.raises(StereoError, match=r"left image has shape \(600, 960\)"):
        compute_depth(left[..., 0], right, *args)
    with pytest.raises(StereoError, match="right image is float32"):
        compute_depth(left, right.astype(np.float32), *args)
    with pytest.raises(StereoError, match="differ in size: 960x600 vs 480x300"):
        compute_depth(left, right[::2, ::2], *args)
    hd = world.unit(0).factory.stereo("HD1200")
    with pytest.raises(StereoError, match="960x600 but the intrinsics are for 1920x1200"):
        compute_depth(left, right, hd.left, hd.right, hd.right_from_left)
    with pytest.raises(StereoError, match="left intrinsics are for 960x600 but right"):
        compute_depth(left, right, st.left, hd.right, st.right_from_left)


def test_uncalibrated_or_swapped_pairs_are_refused(world):
    st = world.unit(0).factory.stereo("SVGA")
    left, right = _svga_pair(st)
    with pytest.raises(StereoError, match=r"baseline of 0\.0 mm.*uncalibrated") as exc:
        compute_depth(left, right, st.left, st.right, Pose(R=np.eye(3)))
    assert isinstance(exc.value, UserError) and isinstance(exc.value, ValueError)
    swapped = Pose(R=st.right_from_left.R.T, t_m=-st.right_from_left.t_m)
    with pytest.raises(StereoError, match="swapped"):
        compute_depth(left, right, st.left, st.right, swapped)
    turned = Pose(R=cv2.Rodrigues(np.array([0.0, 0.5, 0.0]))[0], t_m=st.right_from_left.t_m)
    with pytest.raises(StereoError, match=r"rotates by 28\.6 degrees"):
        compute_depth(left, right, st.left, st.right, turned)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("min_depth_m", 9.0),
        ("match_scale", 2.0),
        ("block_size_px", 4),
        ("min_zncc", 1.5),
        ("zncc_window_px", 2),
        ("lr_max_diff_px", 0.0),
        ("keep_sgbm_within_px", -1.0),
        ("keep_smooth_sgbm_within_px", -1.0),
        ("left_border_slack_px", -2.0),
    ],
)
def test_config_errors_name_the_field_and_value(field, value):
    with pytest.raises(ReconstructConfigError, match=rf"StereoConfig\.{field}={value!r}"):
        StereoConfig(**{field: value})


def test_defaults_follow_the_resolution():
    assert StereoConfig.for_resolution(960).match_scale == 1.0
    assert StereoConfig.for_resolution(1920).match_scale == 0.5
    assert StereoConfig.for_resolution(1920, match_scale=1.0).match_scale == 1.0


def test_a_config_that_sets_other_stereo_keys_keeps_the_resolutions_match_scale():
    """An HD1200 rig whose config tunes one stereo key still matches at half size (not silently
    at full size, ~5x slower); a match_scale it names is kept."""
    from reconstructor.config import ReconstructConfig

    tuned = ReconstructConfig.from_toml("[stereo]\nuniqueness_ratio = 15\n")
    assert tuned.resolved(1920).stereo.match_scale == 0.5
    assert tuned.resolved(960).stereo.match_scale == 1.0
    assert tuned.resolved(1920).stereo.uniqueness_ratio == 15
    named = ReconstructConfig.from_toml("[stereo]\nmatch_scale = 0.8\n")
    assert named.resolved(1920).stereo.match_scale == 0.8
    assert ReconstructConfig().resolved(1920).stereo.match_scale == 0.5
