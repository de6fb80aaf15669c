"""The SGBM+WLS matcher answers up to the right edge of the image: a user's depth maps are not
missing the right-most ``max_disparity`` columns of every camera."""

from __future__ import annotations

import cv2
import numpy as np

from reconstructor.depth.sgbm import (
    RawDisparities,
    SgbmWlsMatcher,
    disparity_range,
    sgbm_disparity,
)
from reconstructor.depth.stereo_config import StereoConfig
from reconstructor.depth.stereo_occlusion import fill_left_border

TRUE_DISPARITY_PX = 21.5


def _rectified_pair(height: int = 160, width: int = 480, seed: int = 0):
    """A textured plane at one known disparity, seen by a rectified pair: the left image at
    ``x`` shows what the right one shows at ``x - d``. The texture fills both images to their
    right edges, so every left pixel from ``x = d`` on has its partner inside the right image."""
    rng = np.random.default_rng(seed)
    scene = cv2.GaussianBlur(
        rng.uniform(0, 255, (height, width + 40, 3)).astype(np.float32), (0, 0), 1.0
    )
    left = scene[:, :width]
    shift = np.float32([[1, 0, -TRUE_DISPARITY_PX], [0, 1, 0]])
    right = cv2.warpAffine(scene, shift, (width, height), flags=cv2.INTER_LINEAR)

    def sensor(img: np.ndarray) -> np.ndarray:  # independent noise in each sensor
        return np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)

    return sensor(left), sensor(right)


def test_a_known_disparity_is_recovered_in_the_right_most_columns():
    """The last 60 columns are as dense and as accurate as the centre. Before the fix (padding
    on the left only) the right-view matcher could not search there, its invalid code read as a
    disparity, and the left-right check emptied the last ~45 columns of this pair."""
    left, right = _rectified_pair()
    disp = SgbmWlsMatcher(StereoConfig()).match(
        left, right, min_disparity_px=4.0, max_disparity_px=60.0
    )
    rows = slice(10, -10)  # the block's own top and bottom border
    for name, cols in (("centre", slice(200, 280)), ("right edge", slice(-60, None))):
        d = disp[rows, cols]
        valid = np.isfinite(d)
        err = np.abs(d[valid] - TRUE_DISPARITY_PX)
        assert valid.mean() >= 0.9, f"{name}: only {valid.mean():.0%} of pixels matched"
        assert np.median(err) < 0.3, f"{name}: median error {np.median(err):.2f} px"
        assert np.mean(err <= 1.0) > 0.98, f"{name}: {np.mean(err > 1.0):.1%} off by > 1 px"
    last = disp[rows, -10:]
    assert np.isfinite(last).mean() >= 0.8  # up to the very last columns


def test_opencv_invalid_codes_are_never_read_as_disparities():
    """OpenCV writes (minDisparity - 1) * 16 where it has no match; for the right-view matcher
    that negates to min_d + num_d, a plausible disparity unless masked."""
    min_d, num_d = 3, 64
    left_codes = np.array([[(min_d - 1) * 16, min_d * 16, (min_d + num_d - 1) * 16, 40 * 16 + 8]])
    right_codes = np.array(
        [[-(min_d + num_d) * 16, -min_d * 16, -(min_d + num_d - 1) * 16, -(40 * 16 + 8)]]
    )
    expected = np.array([[np.nan, min_d, min_d + num_d - 1, 40.5]], np.float32)
    np.testing.assert_array_equal(
        sgbm_disparity(left_codes.astype(np.int16), min_d, num_d), expected
    )
    np.testing.assert_array_equal(
        sgbm_disparity(right_codes.astype(np.int16), min_d, num_d, right_view=True), expected
    )
    # and what OpenCV itself writes for the right view where it has no match
    right_matcher = cv2.ximgproc.createRightMatcher(
        cv2.StereoSGBM.create(minDisparity=min_d, numDisparities=num_d, blockSize=5)
    )
    blank = np.zeros((40, 120), np.uint8)
    raw = right_matcher.compute(blank, blank)
    assert np.isnan(sgbm_disparity(raw, min_d, num_d, right_view=True)[:, -10:]).all()


def test_a_confident_pixel_is_kept_when_its_neighbours_fail_another_check():
    """With ``zncc_warp_failed_by_best`` the photometric check judges a pixel by its window,
    warped by each neighbour's best disparity: a pixel whose SGBM match is right is kept even
    where three rows in four around it have no SGBM match (they hold the WLS map's). Warping
    those neighbours by 0, as the default does, makes the window look uncorrelated and drops it
    (on real pairs, 5-7 % of the answers)."""
    left, right = _rectified_pair()
    shape = left.shape[:2]
    true = np.full(shape, TRUE_DISPARITY_PX, np.float32)
    sgbm_left = true.copy()
    sgbm_left[np.arange(shape[0]) % 4 != 0] = np.nan  # SGBM answered one row in four
    raw = RawDisparities(left=sgbm_left, right=true, filtered=true)
    config = StereoConfig(zncc_warp_failed_by_best=True)
    keep = SgbmWlsMatcher(config).keep(left, right, raw)
    answered_rows = keep[12:-10:4][:, 40:-10]
    assert answered_rows.mean() >= 0.9, f"only {answered_rows.mean():.0%} of the answers kept"
    assert not keep[1::4].any()  # no SGBM match, no answer


class _FixedRaw(SgbmWlsMatcher):
    """The matcher's checks and choice on a given SGBM+WLS matching (what SGBM and WLS answer
    on a slope is hard to stage; the decision after them is what is tested)."""

    def __init__(self, config: StereoConfig, raw: RawDisparities) -> None:
        super().__init__(config)
        self.raw = raw

    def raw_disparities(self, left_rgb, right_rgb, *, min_disparity_px, max_disparity_px):
        return self.raw


def test_where_wls_strays_from_sgbm_by_little_the_answer_is_sgbms_own():
    """With ``keep_sgbm_within_px`` a pixel whose WLS value is 1 px off SGBM's (WLS smoothing a
    slope) is answered with SGBM's disparity, which passes every other check, where the default
    leaves a hole; 3 px off (more than the setting) it stays a hole either way."""
    left, right = _rectified_pair()
    true = np.full(left.shape[:2], TRUE_DISPARITY_PX, np.float32)
    filtered = true.copy()
    filtered[40:80] += 1.0  # WLS 1 px off SGBM: within 1.5 px
    filtered[100:140] += 3.0  # 3 px off: beyond it
    raw = RawDisparities(left=true, right=true, filtered=filtered)
    cols = slice(40, -10)
    for setting in (0.0, 1.5):
        disp = _FixedRaw(StereoConfig(keep_sgbm_within_px=setting), raw).match(
            left, right, min_disparity_px=4.0, max_disparity_px=60.0
        )
        agreeing = disp[10:30, cols]
        assert np.isfinite(agreeing).mean() >= 0.95
        near, far = disp[45:75, cols], disp[105:135, cols]
        assert np.isnan(far).all(), f"setting {setting}: a 3 px disagreement was answered"
        if setting == 0.0:
            assert np.isnan(near).all(), "the default answered where WLS and SGBM differ"
        else:
            assert np.isfinite(near).mean() >= 0.95, f"answered {np.isfinite(near).mean():.0%}"
            np.testing.assert_allclose(near[np.isfinite(near)], TRUE_DISPARITY_PX)


def test_the_left_borders_band_without_a_partner_is_filled_by_its_geometry():
    """The first ``d`` columns of the left image have no partner in the right one: the default
    leaves them holes; with ``fill_left_border`` they take the disparity of the surface they lie
    on (the plane's, exactly), and nothing else changes."""
    left, right = _rectified_pair()
    rows = slice(10, -10)
    band = slice(0, int(TRUE_DISPARITY_PX))  # x < d - 0.5: no partner
    plain, filled = (
        SgbmWlsMatcher(StereoConfig(fill_left_border=on)).match(
            left, right, min_disparity_px=4.0, max_disparity_px=60.0
        )
        for on in (False, True)
    )
    assert np.isfinite(plain[rows, band]).mean() < 0.05
    answered = np.isfinite(filled[rows, band])
    assert answered.mean() >= 0.9, f"only {answered.mean():.0%} of the band filled"
    err = np.abs(filled[rows, band][answered] - TRUE_DISPARITY_PX)
    assert err.max() <= 1.0 and np.median(err) < 0.3
    rest = slice(int(TRUE_DISPARITY_PX) + 2, None)
    np.testing.assert_array_equal(filled[:, rest], plain[:, rest])


def _fill_left_border_loop(disp: np.ndarray, slack_px: float) -> np.ndarray:
    """The slow twin of ``fill_left_border``: one row and one pixel at a time."""
    out = disp.copy()
    for y in range(disp.shape[0]):
        answers = [x for x in range(disp.shape[1]) if np.isfinite(disp[y, x])]
        if not answers or answers[0] == 0:
            continue
        first = answers[0]
        d = disp[y, first]
        if first > d + slack_px:
            continue  # a hole wider than the band: pixels the right camera sees are in it
        for x in range(first):
            if x - d < -0.5:
                out[y, x] = d
    return out


def test_fill_left_border_matches_a_loop_and_leaves_unexplained_holes():
    rng = np.random.default_rng(3)
    disp = rng.uniform(2, 30, (40, 60)).astype(np.float32)
    for y in range(40):  # leading holes of every width, and holes further in
        disp[y, : rng.integers(0, 45)] = np.nan
    disp[rng.uniform(size=disp.shape) < 0.2] = np.nan
    disp[5] = np.nan  # a row without answers
    fast = fill_left_border(disp, 8.0)
    np.testing.assert_array_equal(fast, _fill_left_border_loop(disp, 8.0))
    row = np.full((1, 60), np.nan, np.float32)
    row[0, 40:] = 20.0  # first answer at 40 with d = 20: 12 px wider than band + slack
    assert np.isnan(fill_left_border(row, 8.0)[0, :40]).all()
    row[0, 25:] = 20.0  # first answer at 25: the band is x < 19.5, 20-24 stay holes
    out = fill_left_border(row, 8.0)[0]
    np.testing.assert_array_equal(out[:20], 20.0)
    assert np.isnan(out[20:25]).all()


def test_sgbms_own_is_kept_further_only_where_it_is_smooth():
    """With ``keep_smooth_sgbm_within_px`` a pixel whose WLS value is 2 px off SGBM's (beyond
    ``keep_sgbm_within_px``) is answered with SGBM's own where SGBM's disparity is smooth around
    it, and left a hole within 2 px of a step in SGBM's disparity (a depth edge, where its
    blocks fatten); without the option both are holes."""
    left, right = _rectified_pair()
    true = np.full(left.shape[:2], TRUE_DISPARITY_PX, np.float32)
    sgbm_left = true.copy()
    sgbm_left[:, 300:] += 3.0  # a step in SGBM's own map at column 300
    filtered = true + 2.0  # WLS 2 px off SGBM everywhere
    raw = RawDisparities(left=sgbm_left, right=true, filtered=filtered)
    rows = slice(12, -12)
    for setting in (0.0, 2.5):
        config = StereoConfig(keep_sgbm_within_px=1.5, keep_smooth_sgbm_within_px=setting)
        disp = _FixedRaw(config, raw).match(
            left, right, min_disparity_px=4.0, max_disparity_px=60.0
        )
        smooth, at_step = disp[rows, 60:290], disp[rows, 298:300]
        assert np.isnan(at_step).all(), f"setting {setting}: answered beside SGBM's step"
        if setting == 0.0:
            assert np.isnan(smooth).all(), "answered where WLS strays by 2 px without the option"
        else:
            assert np.isfinite(smooth).mean() >= 0.95, f"answered {np.isfinite(smooth).mean():.0%}"
            np.testing.assert_allclose(smooth[np.isfinite(smooth)], TRUE_DISPARITY_PX)


def test_disparity_range_matches_a_loop():
    rng = np.random.default_rng(4)
    disp = rng.uniform(5, 40, (20, 30)).astype(np.float32)
    disp[rng.uniform(size=disp.shape) < 0.4] = np.nan
    disp[:6, :6] = np.nan  # a window with no disparity at all
    fast = disparity_range(disp, 5)
    slow = np.full_like(disp, np.nan)
    for y in range(disp.shape[0]):
        for x in range(disp.shape[1]):
            win = disp[max(0, y - 2) : y + 3, max(0, x - 2) : x + 3]
            win = win[np.isfinite(win)]
            if win.size:
                slow[y, x] = win.max() - win.min()
    np.testing.assert_allclose(fast, slow, equal_nan=True)
