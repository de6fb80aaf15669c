"""The ZED factory file: what the sim writes, calibration reads back exactly."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from protocol.camera import Resolution
from protocol.formats.zed_conf import ConfFormatError, ZedFactoryCalibration

# A file in the layout the ZED SDK writes for a ZED X, including keys EgoSurg does not use.
REAL_LAYOUT = """[LEFT_CAM_FHD1200]
fx=733.12
fy=733.05
cx=962.4
cy=601.8
k1=-0.0412
k2=0.0169
p1=0.00011
p2=-0.00007
k3=-0.0043
k4=0
k5=0

[RIGHT_CAM_FHD1200]
fx=734.9
fy=734.6
cx=955.1
cy=598.2
k1=-0.0431
k2=0.0181
p1=-0.0001
p2=0.00012
k3=-0.0039

[STEREO]
Baseline=119.72
TY=0.081
TZ=-0.154
CV_FHD1200=0.0021
RX_FHD1200=-0.0013
RZ_FHD1200=0.0007

[MISC]
Sensor_ID=1
"""


def test_round_trip_of_every_simulated_camera(world, tmp_path):
    paths = world.write_factory_files(tmp_path)
    assert sorted(p.name for p in paths) == sorted(f"SN{u.serial}.conf" for u in world.rig)
    for unit in world.rig:
        parsed = ZedFactoryCalibration.read(tmp_path / f"SN{unit.serial}.conf")
        assert parsed.serial == unit.serial
        for res in Resolution:
            for side in ("left", "right"):
                want = unit.sensor(side, res).intrinsics
                got = (parsed.left if side == "left" else parsed.right)[res]
                np.testing.assert_allclose(got.K, want.K, rtol=0, atol=1e-9)
                np.testing.assert_allclose(got.dist, want.dist, rtol=0, atol=1e-12)
                assert (got.width_px, got.height_px) == res.size
            # the stereo transform in the file is the one between the rendered sensors
            st = parsed.stereo(res)
            left, right = unit.sensor("left", res).pose, unit.sensor("right", res).pose
            R_rel = right.R @ left.R.T
            T_rel = right.t_m - R_rel @ left.t_m
            np.testing.assert_allclose(st.R_right_from_left, R_rel, atol=1e-12)
            np.testing.assert_allclose(st.T_right_from_left_m, T_rel, atol=1e-12)
        assert abs(parsed.baseline_mm - unit.factory.baseline_mm) < 1e-9
        assert 110 < parsed.baseline_mm < 130


def test_right_sensor_sits_baseline_to_the_right_of_the_left(world):
    """Sign convention: T = [-Baseline, TY, TZ] puts the right sensor at +x of the left one."""
    unit = world.rig[0]
    st = unit.factory.stereo("HD1200")
    right_centre_in_left = -st.R_right_from_left.T @ st.T_right_from_left_m
    assert right_centre_in_left[0] == pytest.approx(unit.factory.baseline_mm / 1000, abs=1e-3)
    # and in the world: the right sensor's centre is 12 cm along the left camera's +x axis
    left = unit.sensor("left", "HD1200").pose
    right = unit.sensor("right", "HD1200").pose
    offset = left.R @ (right.centre_m - left.centre_m)
    assert offset[0] == pytest.approx(0.12, abs=0.002)


def test_reads_the_real_file_layout_and_derives_missing_modes():
    cal = ZedFactoryCalibration.parse(REAL_LAYOUT, serial=47251234)
    left = cal.left[Resolution.HD1200]
    assert (left.fx_px, left.cx_px, left.dist[0]) == (733.12, 962.4, -0.0412)
    # FHD is a 1920x1080 centre crop: cy - 60; SVGA is binned: everything halved
    assert cal.left[Resolution.HD1080].cy_px == pytest.approx(601.8 - 60)
    assert cal.right[Resolution.SVGA].fx_px == pytest.approx(734.9 / 2)
    st = cal.stereo("SVGA")
    expected_R, _ = cv2.Rodrigues(np.array([-0.0013, 0.0021, 0.0007]))
    np.testing.assert_allclose(st.R_right_from_left, expected_R, atol=1e-15)
    np.testing.assert_allclose(st.T_right_from_left_m, [-0.11972, 0.000081, -0.000154])
    # writing and re-reading keeps every number
    again = ZedFactoryCalibration.parse(cal.to_text(), serial=cal.serial)
    assert again == cal


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("this is not an ini file", ["not a valid ZED .conf"]),
        (REAL_LAYOUT.replace("fx=733.12\n", ""), ["LEFT_CAM_FHD1200", "'fx'"]),
        (REAL_LAYOUT.replace("k2=0.0181", "k2=abc"), ["RIGHT_CAM_FHD1200", "k2", "not a number"]),
        (REAL_LAYOUT.replace("Baseline=119.72", "Baseline=nan"), ["Baseline", "finite"]),
        (REAL_LAYOUT.replace("Baseline=119.72", "Baseline=0.1197"), ["Baseline", "millimetres"]),
        (REAL_LAYOUT.replace("[STEREO]", "[STEREOX]"), ["[STEREO] is missing"]),
        (REAL_LAYOUT.replace("[LEFT_CAM_FHD1200]", "[LEFT_CAM_2K]"), ["LEFT_CAM_FHD1200", "ZED X"]),
        (REAL_LAYOUT.replace("cx=962.4", "cx=2962.4"), ["principal point", "outside"]),
    ],
)
def test_malformed_files_name_the_problem(text, words):
    with pytest.raises(ConfFormatError) as info:
        ZedFactoryCalibration.parse(text, source="SN1.conf")
    for w in words:
        assert w in str(info.value)


def test_missing_file_says_where_to_get_it(tmp_path):
    with pytest.raises(ConfFormatError, match="settings"):
        ZedFactoryCalibration.read(tmp_path / "SN123.conf")


def test_a_five_term_file_writes_back_as_it_was():
    text = ZedFactoryCalibration.parse(REAL_LAYOUT, serial=1).to_text()
    assert "k4" not in text and "k6" not in text  # the stray k4 k5 above are no rational model


def test_reads_the_rational_model_from_the_camera_sections_and_writes_it_back():
    rational = REAL_LAYOUT.replace("k4=0\nk5=0\n", "k4=0.31\nk5=0.052\nk6=0.021\n")
    cal = ZedFactoryCalibration.parse(rational, serial=1)
    left = cal.left[Resolution.HD1200]
    assert left.is_rational and left.dist == (-0.0412, 0.0169, 0.00011, -0.00007, -0.0043,
                                              0.31, 0.052, 0.021)  # fmt: skip
    assert cal.left[Resolution.SVGA].dist == left.dist  # derived modes keep the lens
    assert not cal.right[Resolution.HD1200].is_rational
    again = ZedFactoryCalibration.parse(cal.to_text(), serial=1)
    assert again == cal


def test_a_complete_disto_section_is_the_sensors_rational_model_in_every_mode():
    """As the ZED SDK reads it: [LEFT_DISTO] with all eight terms overrides the camera sections'
    five, in every mode (distortion acts on normalized coordinates); a partial one is ignored."""
    disto = "[LEFT_DISTO]\nk1=-0.05\nk2=0.1\nk3=0.01\nk4=0.3\nk5=0.05\nk6=0.02\np1=0.0\np2=0.0\n"
    cal = ZedFactoryCalibration.parse(REAL_LAYOUT + disto, serial=1)
    for res in Resolution:
        assert cal.left[res].dist == (-0.05, 0.1, 0.0, 0.0, 0.01, 0.3, 0.05, 0.02)
        assert not cal.right[res].is_rational
    assert ZedFactoryCalibration.parse(cal.to_text(), serial=1) == cal
    partial = ZedFactoryCalibration.parse(REAL_LAYOUT + disto.replace("k6=0.02\n", ""), serial=1)
    assert not partial.left[Resolution.HD1200].is_rational
