"""Exports of a rig calibration: write, read back and reproject; and each format's conventions,
checked with an independent projection written from the format's own definition."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import cv2
import numpy as np
import pytest

from calibration.report.exports import (
    export_colmap,
    export_nerfstudio,
    export_opencv_yaml,
    fit_radial,
    fit_without_k3,
    read_colmap,
    read_nerfstudio,
    read_opencv_yaml,
    rotation_to_quaternion,
    undistorted_pinhole,
)
from protocol.camera import Camera, undistort_to_normalized
from protocol.formats.rig_calibration import CalibrationFileError, RigCalibration
from protocol.formats.trajectory import matrix_from_quat_wxyz

EXACT_PX = 1e-6


@pytest.fixture(scope="module")
def rig(sim_true_rig: RigCalibration) -> RigCalibration:
    """The sim's rig with five-term lenses only: its rational sensor refitted to the five terms
    (within a few pixels of it). The rational model's exports have their own tests below."""
    sensors = []
    for s in sim_true_rig.sensors:
        if s.intrinsics.is_rational:
            (k1, k2, k3), _, _ = fit_radial(s.intrinsics, 3)
            p1, p2 = s.intrinsics.dist[2:4]
            s = replace(s, intrinsics=replace(s.intrinsics, dist=(k1, k2, p1, p2, k3)))
        sensors.append(s)
    return replace(sim_true_rig, sensors=tuple(sensors))


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    """3D points filling the room's working volume (metres)."""
    rng = np.random.default_rng(1)
    return np.column_stack(
        [rng.uniform(-2.5, 2.5, 4000), rng.uniform(-2.4, 2.4, 4000), rng.uniform(0.1, 2.2, 4000)]
    )


def without_k3(cal: RigCalibration) -> RigCalibration:
    sensors = tuple(
        replace(s, intrinsics=replace(s.intrinsics, dist=(*s.intrinsics.dist[:4], 0.0)))
        for s in cal.sensors
    )
    return replace(cal, sensors=sensors)


def visible(cam: Camera, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and a mask of the points the sensor really sees. Far outside the field of view the
    five-term polynomial folds back (k3 < 0), landing unseen points inside the image; the mask
    keeps only rays no wider than the image corners' rays."""
    px, z = cam.project(pts)
    i = cam.intrinsics
    w, h = i.width_px - 1, i.height_px - 1
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    r_max = np.linalg.norm(undistort_to_normalized(corners, i), axis=1).max()
    X = cam.pose.transform(pts)
    r = np.hypot(X[:, 0], X[:, 1]) / np.maximum(X[:, 2], 1e-9)
    inside = (px[:, 0] >= 0) & (px[:, 0] <= i.width_px - 1) & (px[:, 1] >= 0)
    return px, (z > 0.3) & (r <= r_max) & inside & (px[:, 1] <= i.height_px - 1)


def reprojection_gap(a: RigCalibration, b: RigCalibration, pts: np.ndarray) -> np.ndarray:
    """Pixel distance between the two calibrations' projections of every visible point."""
    assert [s.name for s in a.sensors] == [s.name for s in b.sensors]
    gaps = []
    for sa, sb in zip(a.sensors, b.sensors, strict=True):
        assert (sa.camera_serial, sa.side) == (sb.camera_serial, sb.side)
        pa, ok = visible(sa.camera, pts)
        pb, _ = sb.camera.project(pts)
        assert ok.sum() > 100, f"{sa.name} sees too few test points"
        gaps.append(np.linalg.norm(pa[ok] - pb[ok], axis=1))
    return np.concatenate(gaps)


# -- OpenCV YAML --------------------------------------------------------------------------------
def test_opencv_yaml_round_trip_reprojects_exactly(rig, points, tmp_path):
    path = export_opencv_yaml(rig, tmp_path / "rig.yaml")
    back = read_opencv_yaml(path)
    assert reprojection_gap(rig, back, points).max() < EXACT_PX
    assert back.resolution == rig.resolution and back.world_frame == rig.world_frame
    text = path.read_text()
    assert "metres" in text and "world-to-camera" in text


def test_opencv_yaml_reads_with_plain_opencv(rig, points, tmp_path):
    path = export_opencv_yaml(rig, tmp_path / "rig.yaml")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    node = fs.getNode("sensors")
    assert node.size() == len(rig.sensors) == 8
    for k, s in enumerate(rig.sensors):
        n = node.at(k)
        rvec, _ = cv2.Rodrigues(n.getNode("R").mat())
        px, _ = cv2.projectPoints(
            points, rvec, n.getNode("T").mat(), n.getNode("K").mat(), n.getNode("D").mat()
        )
        want, ok = visible(s.camera, points)
        assert np.abs(px.reshape(-1, 2)[ok] - want[ok]).max() < EXACT_PX
        assert n.getNode("image_width").real() == 1920
    fs.release()


def test_opencv_yaml_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(CalibrationFileError, match="no such"):
        read_opencv_yaml(tmp_path / "nope.yaml")


# -- COLMAP -------------------------------------------------------------------------------------
def test_colmap_opencv_round_trip_is_exact_without_k3(rig, points, tmp_path, caplog):
    cal = without_k3(rig)
    with caplog.at_level(logging.WARNING, logger="calibration.report.exports"):
        export_colmap(cal, tmp_path)
    assert not caplog.records
    back = read_colmap(tmp_path)
    assert reprojection_gap(cal, back, points).max() < EXACT_PX
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "cameras.txt",
        "images.txt",
        "points3D.txt",
    ]


def test_colmap_full_opencv_keeps_k3_exactly(rig, points, tmp_path):
    export_colmap(rig, tmp_path, model="FULL_OPENCV")
    assert reprojection_gap(rig, read_colmap(tmp_path), points).max() < EXACT_PX


def test_colmap_opencv_reports_k3_and_refits_k1_k2(rig, points, tmp_path, caplog):
    """OPENCV has no k3. Plainly dropping the ZED lenses' k3 (about -0.004) moves points of the room
    by up to about 60 px (130 px at the image corners). Refitting k1 and k2 leaves, measured on
    this rig: for points in the room, median 0.36 px, p95 1.3 px, max 2.3 px; over a grid
    covering the whole image, p95 1.1-2.2 px and 6-15 px in the extreme corners. The bounds below
    are those numbers with some slack; the warning must name every sensor."""
    with caplog.at_level(logging.WARNING, logger="calibration.report.exports"):
        export_colmap(rig, tmp_path)
    message = " ".join(r.getMessage() for r in caplog.records)
    assert "no k3" in message and "FULL_OPENCV" in message
    assert all(s.name in message for s in rig.sensors)
    gap = reprojection_gap(rig, read_colmap(tmp_path), points)
    dropped = reprojection_gap(rig, without_k3(rig), points)
    assert dropped.max() > 30  # why the refit exists
    assert np.percentile(gap, 95) < 2.0 and gap.max() < 4.0
    for s in rig.sensors:
        _, worst, p95 = fit_without_k3(s.intrinsics)
        assert p95 < 3.0 and worst < 16.0


def test_colmap_pinhole_describes_the_undistorted_images(rig, points, tmp_path):
    export_colmap(rig, tmp_path, model="PINHOLE")
    back = read_colmap(tmp_path)
    for s, b in zip(rig.sensors, back.sensors, strict=True):
        new = undistorted_pinhole(s.intrinsics)
        assert b.intrinsics == new and not b.intrinsics.has_distortion
        # undistorting the real image to `new` (as the docstring's remap does) maps each pixel
        # where the exported pinhole projects it
        px, ok = visible(s.camera, points)
        flat = undistort_to_normalized(px[ok], s.intrinsics) * [new.fx_px, new.fy_px] + [
            new.cx_px,
            new.cy_px,
        ]
        want, _ = b.camera.project(points[ok])
        assert np.abs(flat - want).max() < 1e-4
        assert "PINHOLE" in (tmp_path / "cameras.txt").read_text()


def _opencv_distort(x: np.ndarray, y: np.ndarray, k: list[float]) -> tuple[np.ndarray, ...]:
    """OpenCV's Brown-Conrady model written out (k1 k2 p1 p2 [k3])."""
    k1, k2, p1, p2, k3 = [*k, 0.0][:5]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (
        x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def test_colmap_text_follows_colmaps_conventions(rig, points, tmp_path):
    """Project with COLMAP's definitions, from the text alone: world-to-camera quaternion
    (w, x, y, z) and translation, OPENCV params, pixel centres at +0.5."""
    cal = without_k3(rig)
    export_colmap(cal, tmp_path)
    cams = {}
    for line in (tmp_path / "cameras.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            f = line.split()
            assert f[1] == "OPENCV" and (f[2], f[3]) == ("1920", "1200")
            cams[f[0]] = [float(v) for v in f[4:]]
    lines = [ln for ln in (tmp_path / "images.txt").read_text().splitlines() if ln[:1] != "#"]
    assert len(lines) == 16 and all(ln == "" for ln in lines[1::2])
    for s, line in zip(cal.sensors, lines[0::2], strict=True):
        f = line.split()
        assert f[9] == f"SN{s.camera_serial}_{s.side}.png"
        qw, qx, qy, qz = map(float, f[1:5])
        R = np.array(
            [
                [1 - 2 * (qy**2 + qz**2), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                [2 * (qx * qy + qw * qz), 1 - 2 * (qx**2 + qz**2), 2 * (qy * qz - qw * qx)],
                [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx**2 + qy**2)],
            ]
        )
        X = points @ R.T + np.array([float(v) for v in f[5:8]])
        fx, fy, cx, cy, *k = cams[f[8]]
        xd, yd = _opencv_distort(X[:, 0] / X[:, 2], X[:, 1] / X[:, 2], k)
        colmap_px = np.column_stack([fx * xd + cx, fy * yd + cy])
        want, ok = visible(s.camera, points)
        assert np.abs(colmap_px[ok] - (want[ok] + 0.5)).max() < EXACT_PX


def test_colmap_rejects_unknown_image_names(rig, tmp_path):
    export_colmap(without_k3(rig), tmp_path)
    p = tmp_path / "images.txt"
    p.write_text(p.read_text().replace(f"SN{rig.sensors[0].camera_serial}_left", "frame0001"))
    with pytest.raises(CalibrationFileError, match="SN<serial>_<side>"):
        read_colmap(tmp_path)


def test_quaternions_round_trip_including_half_turns():
    rng = np.random.default_rng(3)
    rots = [cv2.Rodrigues(rng.normal(size=3))[0] for _ in range(50)]
    rots += [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for R in rots:
        q = rotation_to_quaternion(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        assert np.abs(matrix_from_quat_wxyz(q) - R).max() < 1e-12


# -- nerfstudio ---------------------------------------------------------------------------------
def test_nerfstudio_round_trip_reprojects_exactly(rig, points, tmp_path):
    path = export_nerfstudio(rig, tmp_path / "transforms.json")
    back = read_nerfstudio(path)
    assert reprojection_gap(rig, back, points).max() < EXACT_PX
    assert back.resolution == rig.resolution


def test_nerfstudio_transforms_follow_opengl_camera_axes(rig, points, tmp_path):
    """Project from the JSON alone with nerfstudio's definitions: camera-to-world with x right,
    y up, z back (the camera looks along -z), OPENCV distortion with k3, pixel centres at +0.5."""
    doc = json.loads(export_nerfstudio(rig, tmp_path).read_text())
    assert doc["camera_model"] == "OPENCV" and len(doc["frames"]) == 8
    for s, fr in zip(rig.sensors, doc["frames"], strict=True):
        assert fr["file_path"] == f"images/SN{s.camera_serial}_{s.side}.png"
        assert (fr["w"], fr["h"], fr["camera_model"]) == (1920, 1200, "OPENCV")
        c2w = np.asarray(fr["transform_matrix"])
        assert np.allclose(c2w[3], [0, 0, 0, 1])
        assert np.allclose(c2w[:3, 3], s.pose.centre_m)
        X = (np.c_[points, np.ones(len(points))] @ np.linalg.inv(c2w).T)[:, :3]
        depth = -X[:, 2]
        x, y = X[:, 0] / depth, -X[:, 1] / depth
        k = [fr["k1"], fr["k2"], fr["p1"], fr["p2"], fr["k3"]]
        xd, yd = _opencv_distort(x, y, k)
        ns_px = np.column_stack([fr["fl_x"] * xd + fr["cx"], fr["fl_y"] * yd + fr["cy"]])
        want, ok = visible(s.camera, points)
        assert np.abs(ns_px[ok] - (want[ok] + 0.5)).max() < EXACT_PX
        assert (depth[ok] > 0).all()


def test_nerfstudio_refuses_what_opencv_cannot_express(rig, tmp_path):
    path = export_nerfstudio(rig, tmp_path)
    doc = json.loads(path.read_text())
    doc["frames"][0]["k4"] = 0.01
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationFileError, match="k4"):
        read_nerfstudio(path)


# -- the rational lens model (ZED X: k1 k2 p1 p2 k3 k4 k5 k6) -----------------------------------
RATIONAL = (-0.05, 0.1, 1e-4, -1e-4, 0.01, 0.3, 0.05, 0.02)


@pytest.fixture(scope="module")
def rational_rig(rig: RigCalibration) -> RigCalibration:
    """The rig with its first camera's two sensors on the rational model."""
    sensors = tuple(
        replace(s, intrinsics=replace(s.intrinsics, dist=RATIONAL)) if k < 2 else s
        for k, s in enumerate(rig.sensors)
    )
    return replace(rig, sensors=sensors)


def test_rational_lenses_round_trip_exactly_through_opencv_yaml(rational_rig, points, tmp_path):
    back = read_opencv_yaml(export_opencv_yaml(rational_rig, tmp_path / "rig.yaml"))
    assert (
        back.sensors[0].intrinsics.dist == RATIONAL and not back.sensors[2].intrinsics.is_rational
    )
    assert reprojection_gap(rational_rig, back, points).max() < EXACT_PX


def test_colmap_writes_rational_lenses_as_full_opencv(rational_rig, points, tmp_path, caplog):
    """COLMAP's models are per camera: the rational sensors become FULL_OPENCV (exact), the
    others stay OPENCV (refitted, named in the warning); FULL_OPENCV reads back exactly."""
    with caplog.at_level(logging.WARNING, logger="calibration.report.exports"):
        export_colmap(rational_rig, tmp_path)
    models = [
        ln.split()[1]
        for ln in (tmp_path / "cameras.txt").read_text().splitlines()
        if ln and not ln.startswith("#")
    ]
    assert models == ["FULL_OPENCV"] * 2 + ["OPENCV"] * 6
    message = " ".join(r.getMessage() for r in caplog.records)
    assert rational_rig.sensors[0].name not in message and rational_rig.sensors[2].name in message
    back = read_colmap(tmp_path)
    assert back.sensors[1].intrinsics.dist == RATIONAL
    two = replace(rational_rig, sensors=rational_rig.sensors[:2])
    assert reprojection_gap(two, replace(back, sensors=back.sensors[:2]), points).max() < EXACT_PX
    export_colmap(rational_rig, tmp_path, model="FULL_OPENCV")
    assert reprojection_gap(rational_rig, read_colmap(tmp_path), points).max() < EXACT_PX


def test_nerfstudio_refits_rational_lenses_with_a_warning(rational_rig, points, tmp_path, caplog):
    """nerfstudio's OPENCV model is polynomial: a rational lens is refitted to k1 k2 k3 over the
    whole image, the warning names the sensor and the error, and the file reads back."""
    with caplog.at_level(logging.WARNING, logger="calibration.report.exports"):
        path = export_nerfstudio(rational_rig, tmp_path)
    message = " ".join(r.getMessage() for r in caplog.records)
    assert rational_rig.sensors[0].name in message and "rational" in message
    assert rational_rig.sensors[2].name not in message
    back = read_nerfstudio(path)
    assert not back.sensors[0].intrinsics.is_rational
    exact = replace(rational_rig, sensors=rational_rig.sensors[2:])
    assert reprojection_gap(exact, replace(back, sensors=back.sensors[2:]), points).max() < 1e-6
    _, worst, p95 = fit_radial(rational_rig.sensors[0].intrinsics, 3)
    gap = reprojection_gap(
        replace(rational_rig, sensors=rational_rig.sensors[:2]),
        replace(back, sensors=back.sensors[:2]),
        points,
    )
    print(
        f"rational -> k1 k2 k3: grid p95 {p95:.2f} px, worst {worst:.2f} px, room {gap.max():.2f}"
    )
    assert gap.max() <= worst + 1e-6


def test_the_rig_calibration_file_round_trips_rational_lenses(rational_rig, points, tmp_path):
    back = RigCalibration.read(rational_rig.write(tmp_path / "calibration.toml"))
    assert [s.intrinsics for s in back.sensors] == [s.intrinsics for s in rational_rig.sensors]
    assert reprojection_gap(rational_rig, back, points).max() == 0.0
