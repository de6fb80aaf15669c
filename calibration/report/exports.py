"""Export a rig calibration for other tools, and read each export back.

Three formats, each with units and conventions written into the file itself:

- **OpenCV YAML** (``cv2.FileStorage``): per sensor ``K`` (3x3), ``D`` (1x5: k1 k2 p1 p2 k3, or
  1x8 with k4 k5 k6 for a rational lens, as ``cv2.calibrateCamera`` writes them),
  ``R`` (3x3) and ``T`` (3x1) with ``x_cam = R @ x_world + T`` in metres, OpenCV camera axes
  (x right, y down, z forward), pixel (0, 0) at the centre of the top-left pixel. Exact.
- **COLMAP text model** (``cameras.txt``, ``images.txt``, empty ``points3D.txt``): one camera and
  one image per sensor, the image named ``SN<serial>_<side>.png``. Poses are world-to-camera
  ``QW QX QY QZ TX TY TZ`` (Hamilton quaternion of R, T in metres), as COLMAP stores them.
  Models:

  - ``OPENCV`` (default; what gsplat and nerfstudio's COLMAP loaders read):
    ``fx fy cx cy k1 k2 p1 p2``. It has **no k3**. The ZED factory lenses do have a k3, and just
    dropping it moves the image corners by tens of pixels, so for k3 != 0 we refit k1 and k2 to the
    five-term model over the whole image and log a warning with the worst remaining error. A
    sensor with the rational model (k4..k6, which no refit of k1 k2 approaches) is written as
    ``FULL_OPENCV`` instead: COLMAP's models are per camera, so one file may hold both.
  - ``FULL_OPENCV``: ``fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6``, OpenCV's rational model (k4 = k5 =
    k6 = 0 for a five-term lens): exact.
  - ``PINHOLE``: ``fx fy cx cy`` for *undistorted* images, the only kind the original 3DGS code
    reads. It builds its projection from the field of view alone, so it also assumes the principal
    point is the image centre. We therefore write :func:`undistorted_pinhole` (same focal lengths,
    centred principal point); undistort each image to exactly that camera first::

        new = undistorted_pinhole(intr)
        maps = cv2.initUndistortRectifyMap(intr.K, intr.dist_array, None, new.K, size, cv2.CV_32FC1)
        flat = cv2.remap(image, *maps, cv2.INTER_LINEAR)

    Barrel distortion pushes the undistorted image's edges outwards, so a thin rim is cropped.

- **nerfstudio** ``transforms.json``: per frame ``file_path`` (``images/SN<serial>_<side>.png``),
  ``transform_matrix`` (camera-to-world, OpenGL/nerfstudio camera axes: x right, y up, z back, i.e.
  OpenCV's y and z negated), ``fl_x fl_y cx cy w h k1 k2 k3 k4 p1 p2``, and ``camera_model``
  ``"OPENCV"`` (top level, where nerfstudio reads it, and per frame). nerfstudio's OPENCV model
  keeps k3 (its radial polynomial runs to k4 r^8), so this export is exact for a five-term lens.
  It has no rational model: for a rational lens k1 k2 k3 are refitted over the whole image (k4 =
  0, so the file stays readable as OpenCV's five terms) with a warning giving the remaining error.
  The world frame is ours
  (metres, z up from the floor); nerfstudio may re-centre and re-orient it when it loads.

**Pixel origin.** COLMAP, nerfstudio and gsplat put the *corner* of the top-left pixel at (0, 0),
so the centre of that pixel is (0.5, 0.5); OpenCV (and EgoSurg) put its centre at (0, 0). Both
COLMAP and nerfstudio exports therefore write ``cx + 0.5`` and ``cy + 0.5``, and the readers
subtract it again. Forgetting this shifts every splat by half a pixel.
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from protocol.camera import DIST_TERMS, Intrinsics, Pose, Resolution, undistort_to_normalized
from protocol.formats.rig_calibration import CalibrationFileError, RigCalibration, SensorCalibration
from protocol.formats.trajectory import matrix_from_quat_wxyz

log = logging.getLogger(__name__)

EXPORT_FORMAT_VERSION = 1
CONVENTIONS = (
    "units: metres (translations) and pixels (intrinsics); camera axes OpenCV: x right, y down, "
    "z forward; pose world-to-camera: x_cam = R @ x_world + T; distortion OpenCV k1 k2 p1 p2 k3 "
    "(+ k4 k5 k6: rational model); "
    "pixel (0, 0) is the centre of the top-left pixel"
)
PIXEL_CENTRE_SHIFT_PX = 0.5  # COLMAP/nerfstudio pixel origin minus OpenCV's
COLMAP_MODELS = ("OPENCV", "FULL_OPENCV", "PINHOLE")
_NAME_RE = re.compile(r"SN(\d+)[_-](left|right)")
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips a camera's y and z axes (self-inverse)


def image_name(sensor: SensorCalibration, ext: str = "png") -> str:
    """The image name the COLMAP and nerfstudio exports use for one sensor."""
    return f"SN{sensor.camera_serial}_{sensor.side}.{ext}"


def undistorted_pinhole(intr: Intrinsics) -> Intrinsics:
    """The distortion-free, centred pinhole that PINHOLE exports describe (same focal lengths)."""
    return Intrinsics(
        width_px=intr.width_px,
        height_px=intr.height_px,
        fx_px=intr.fx_px,
        fy_px=intr.fy_px,
        cx_px=(intr.width_px - 1) / 2,
        cy_px=(intr.height_px - 1) / 2,
    )


def fit_without_k3(intr: Intrinsics) -> tuple[tuple[float, float, float, float], float, float]:
    """(k1, k2, p1, p2) that best reproduce the five-term model over the whole image, and the
    worst and 95th-percentile remaining error in pixels over the image.

    p1 and p2 are kept; k1 and k2 are a linear least-squares fit in pixel units on a grid of image
    points, corners included. For a ZED X lens (k3 about -0.004) plainly dropping k3 moves the
    corners by about 130 px; the refit leaves about 1.3 px typical, 2 px at the 95th percentile
    and 6-15 px in the extreme corners."""
    k1, k2, p1, p2 = intr.dist[:4]
    if not any(intr.dist[4:]):
        return (k1, k2, p1, p2), 0.0, 0.0
    radial, worst, p95 = fit_radial(intr, 2)
    return (radial[0], radial[1], p1, p2), worst, p95


def fit_radial(intr: Intrinsics, terms: int) -> tuple[tuple[float, ...], float, float]:
    """``terms`` polynomial radial coefficients (k1, k2[, k3]) that, with the lens's own p1 and p2,
    best reproduce its distortion over the whole image; and the worst and 95th-percentile
    remaining error in pixels. A linear least-squares fit in pixel units on a grid of image
    points, corners included, each undistorted through the full model (five terms or rational)."""
    p1, p2 = intr.dist[2:4]
    u, v = np.meshgrid(
        np.linspace(0, intr.width_px - 1, 49), np.linspace(0, intr.height_px - 1, 31)
    )
    grid = np.column_stack([u.ravel(), v.ravel()])
    x, y = undistort_to_normalized(grid, intr).T
    xd = (grid[:, 0] - intr.cx_px) / intr.fx_px
    yd = (grid[:, 1] - intr.cy_px) / intr.fy_px
    r2 = x * x + y * y
    tx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    ty = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    powers = np.column_stack([r2**j for j in range(1, terms + 1)])
    A = np.vstack([intr.fx_px * x[:, None] * powers, intr.fy_px * y[:, None] * powers])
    b = np.concatenate([intr.fx_px * (xd - x - tx), intr.fy_px * (yd - y - ty)])
    coeffs, *_ = np.linalg.lstsq(A, b, rcond=None)
    radial = 1 + powers @ coeffs
    px = np.column_stack(
        [intr.fx_px * (x * radial + tx) + intr.cx_px, intr.fy_px * (y * radial + ty) + intr.cy_px]
    )
    err = np.linalg.norm(px - grid, axis=1)
    return tuple(float(c) for c in coeffs), float(err.max()), float(np.percentile(err, 95))


# -- OpenCV YAML --------------------------------------------------------------------------------
def export_opencv_yaml(cal: RigCalibration, path: Path | str) -> Path:
    """Write every sensor's K, D, R, T and image size with ``cv2.FileStorage`` (YAML)."""
    import cv2

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    try:
        fs.writeComment(
            f"EgoSurg rig calibration, OpenCV YAML export, format {EXPORT_FORMAT_VERSION}"
        )
        fs.writeComment(
            "K: 3x3 camera matrix [px]; D: k1 k2 p1 p2 k3 [k4 k5 k6]; R, T: world-to-camera"
        )
        fs.writeComment("x_cam = R @ x_world + T, T in metres, OpenCV camera axes")
        fs.write("format", "egosurg-rig-calibration-opencv")
        fs.write("format_version", EXPORT_FORMAT_VERSION)
        fs.write("conventions", CONVENTIONS)
        fs.write("resolution", cal.resolution.value)
        fs.write("world_frame", cal.world_frame)
        fs.write("sensor_count", len(cal.sensors))
        fs.startWriteStruct("sensors", cv2.FileNode_SEQ)
        for s in cal.sensors:
            i = s.intrinsics
            fs.startWriteStruct("", cv2.FileNode_MAP)
            fs.write("name", s.name)
            fs.write("camera_serial", str(s.camera_serial))  # a string: serials may pass 2^31
            fs.write("side", s.side)
            fs.write("image_width", i.width_px)
            fs.write("image_height", i.height_px)
            fs.write("K", i.K)
            fs.write("D", i.dist_array.reshape(1, -1))
            fs.write("R", s.pose.R)
            fs.write("T", s.pose.t_m.reshape(3, 1))
            fs.endWriteStruct()
        fs.endWriteStruct()
    finally:
        fs.release()
    return p


def read_opencv_yaml(path: Path | str) -> RigCalibration:
    """Read a file written by :func:`export_opencv_yaml`."""
    import cv2

    p = Path(path)
    if not p.is_file():
        raise CalibrationFileError(f"{p}: no such OpenCV calibration file")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CalibrationFileError(f"{p}: not an OpenCV YAML file: {exc}") from None
    try:
        seq = fs.getNode("sensors")
        if seq.empty() or not seq.isSeq():
            raise CalibrationFileError(f"{p}: no 'sensors' list; was it written by EgoSurg?")
        sensors = []
        for k in range(seq.size()):
            node = seq.at(k)
            where = f"{p} sensors[{k}]"

            def get(key: str, node: Any = node, where: str = where) -> Any:
                n = node.getNode(key)
                if n.empty():
                    raise CalibrationFileError(f"{where}: missing {key!r}")
                return n

            K = get("K").mat()
            D = get("D").mat().reshape(-1)
            if K.shape != (3, 3) or D.size not in DIST_TERMS:
                raise CalibrationFileError(f"{where}: K must be 3x3 and D must have 5 or 8 terms")
            intr = Intrinsics(
                width_px=int(get("image_width").real()),
                height_px=int(get("image_height").real()),
                fx_px=float(K[0, 0]),
                fy_px=float(K[1, 1]),
                cx_px=float(K[0, 2]),
                cy_px=float(K[1, 2]),
                dist=tuple(float(d) for d in D),
            )
            sensors.append(
                _sensor(
                    get("name").string(),
                    int(get("camera_serial").string()),
                    get("side").string(),
                    intr,
                    get("R").mat(),
                    get("T").mat(),
                    where,
                )
            )
        res = fs.getNode("resolution")
        frame = fs.getNode("world_frame")
        return RigCalibration(
            sensors=tuple(sensors),
            resolution=Resolution.parse(res.string()) if not res.empty() else _res(sensors),
            world_frame=frame.string() if not frame.empty() else "floor",
        )
    finally:
        fs.release()


# -- COLMAP -------------------------------------------------------------------------------------
def export_colmap(cal: RigCalibration, out_dir: Path | str, model: str = "OPENCV") -> Path:
    """Write a COLMAP text model (cameras.txt, images.txt, points3D.txt) into ``out_dir``."""
    model = model.upper()
    if model not in COLMAP_MODELS:
        raise ValueError(f"model={model!r} is not supported; use one of {', '.join(COLMAP_MODELS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    head = [
        f"# EgoSurg rig calibration, COLMAP text export, format {EXPORT_FORMAT_VERSION}",
        f"# egosurg: resolution={cal.resolution.value} world_frame={cal.world_frame}",
        "# units: metres; pose world-to-camera (COLMAP), OpenCV camera axes; pixel (0.5, 0.5) is "
        "the centre of the top-left pixel (COLMAP), so cx, cy are OpenCV's + 0.5",
    ]
    cams = [
        *head,
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
    ]
    if model == "OPENCV":
        cams.append("# OPENCV params: fx fy cx cy k1 k2 p1 p2 (no k3: k1 k2 refit where k3 != 0)")
        if any(s.intrinsics.is_rational for s in cal.sensors):
            cams.append("# FULL_OPENCV for the rational lenses: + k3 k4 k5 k6, exact")
    elif model == "FULL_OPENCV":
        cams.append("# FULL_OPENCV params: fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 (0 if not rational)")
    else:
        cams.append("# PINHOLE params: fx fy cx cy; undistort images to this centred pinhole first")
    cams.append(f"# Number of cameras: {len(cal.sensors)}")
    imgs = [
        *head,
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(cal.sensors)}, mean observations per image: 0",
    ]
    refit = []
    for idx, s in enumerate(cal.sensors, start=1):
        i = s.intrinsics
        if model == "PINHOLE":
            i = undistorted_pinhole(i)
        cx, cy = i.cx_px + PIXEL_CENTRE_SHIFT_PX, i.cy_px + PIXEL_CENTRE_SHIFT_PX
        params = [i.fx_px, i.fy_px, cx, cy]
        line_model = "FULL_OPENCV" if model == "OPENCV" and i.is_rational else model
        if line_model == "OPENCV":
            dist4, worst, p95 = fit_without_k3(i)
            if i.dist[4] != 0.0:
                refit.append(
                    f"{s.name} (k3={i.dist[4]:g}: error p95 {p95:.1f} px, corners {worst:.1f} px)"
                )
            params += list(dist4)
        elif line_model == "FULL_OPENCV":
            params += list(i.dist8)
        cams.append(f"{idx} {line_model} {i.width_px} {i.height_px} " + " ".join(map(repr, params)))
        q = rotation_to_quaternion(s.pose.R)
        vals = [*q, *s.pose.t_m]
        imgs += [f"{idx} " + " ".join(repr(float(v)) for v in vals) + f" {idx} {image_name(s)}", ""]
    if refit:
        log.warning(
            "COLMAP's OPENCV model has no k3: refitted k1 and k2 without it for %s. For exact "
            "geometry use model='FULL_OPENCV' if the consumer reads it, or undistort the images "
            "and use model='PINHOLE'",
            ", ".join(refit),
        )
    (out / "cameras.txt").write_text("\n".join(cams) + "\n")
    (out / "images.txt").write_text("\n".join(imgs) + "\n")
    (out / "points3D.txt").write_text(
        "\n".join(
            [
                *head,
                "# 3D point list with one line of data per point: (none; poses come from the wand)",
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                "# Number of points: 0, mean track length: 0",
            ]
        )
        + "\n"
    )
    return out


def read_colmap(out_dir: Path | str) -> RigCalibration:
    """Read a COLMAP text model whose image names carry ``SN<serial>_<side>``."""
    d = Path(out_dir)
    try:
        cam_lines = (d / "cameras.txt").read_text().splitlines()
        img_lines = (d / "images.txt").read_text().splitlines()
    except FileNotFoundError as exc:
        raise CalibrationFileError(
            f"{d}: not a COLMAP text model ({exc.filename} missing)"
        ) from None
    cameras: dict[int, Intrinsics] = {}
    for n, line in enumerate(cam_lines, start=1):
        if not line.strip() or line.startswith("#"):
            continue
        f = line.split()
        try:
            cameras[int(f[0])] = _colmap_intrinsics(
                f[1], int(f[2]), int(f[3]), [float(v) for v in f[4:]]
            )
        except (ValueError, IndexError) as exc:
            raise CalibrationFileError(f"{d / 'cameras.txt'} line {n}: {exc}") from None
    sensors = []
    data = [(n, ln) for n, ln in enumerate(img_lines, start=1) if not ln.startswith("#")]
    for n, line in data[0::2]:  # every other line lists the image's 2D points
        if not line.strip():
            continue
        f = line.split()
        where = f"{d / 'images.txt'} line {n}"
        if len(f) < 10:
            raise CalibrationFileError(f"{where}: expected 10 fields, got {len(f)}")
        serial, side = _parse_name(f[9], where)
        cam_id = int(f[8])
        if cam_id not in cameras:
            raise CalibrationFileError(f"{where}: camera {cam_id} is not in cameras.txt")
        R = matrix_from_quat_wxyz(np.array([float(v) for v in f[1:5]]))
        t = np.array([float(v) for v in f[5:8]])
        sensors.append(_sensor(f"SN{serial}-{side}", serial, side, cameras[cam_id], R, t, where))
    if not sensors:
        raise CalibrationFileError(f"{d / 'images.txt'}: no images")
    meta = _egosurg_header(cam_lines)
    return RigCalibration(
        sensors=tuple(sensors),
        resolution=Resolution.parse(meta["resolution"]) if "resolution" in meta else _res(sensors),
        world_frame=meta.get("world_frame", "floor"),
    )


def _colmap_intrinsics(model: str, w: int, h: int, p: list[float]) -> Intrinsics:
    """One cameras.txt line's intrinsics, in OpenCV's pixel convention."""
    counts = {
        "SIMPLE_PINHOLE": 3,
        "PINHOLE": 4,
        "SIMPLE_RADIAL": 4,
        "RADIAL": 5,
        "OPENCV": 8,
        "FULL_OPENCV": 12,
    }
    if model not in counts:
        raise ValueError(f"camera model {model} cannot be read; use one of {', '.join(counts)}")
    if len(p) != counts[model]:
        raise ValueError(f"{model} needs {counts[model]} parameters, got {len(p)}")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        (fx, cx, cy), fy = p[:3], p[0]
        k = [*p[3:], 0.0, 0.0]
        dist = [k[0], k[1], 0.0, 0.0, 0.0]
    else:
        fx, fy, cx, cy = p[:4]
        dist = [*p[4:9], 0.0, 0.0, 0.0, 0.0, 0.0][:5]  # OPENCV: k1 k2 p1 p2; FULL: + k3
        if any(v != 0.0 for v in p[9:]):
            dist += p[9:]  # FULL_OPENCV's k4..k6: OpenCV's rational model
    s = PIXEL_CENTRE_SHIFT_PX
    return Intrinsics(
        width_px=w,
        height_px=h,
        fx_px=fx,
        fy_px=fy,
        cx_px=cx - s,
        cy_px=cy - s,
        dist=tuple(dist),
    )


# -- nerfstudio ---------------------------------------------------------------------------------
def export_nerfstudio(cal: RigCalibration, path: Path | str, image_dir: str = "images") -> Path:
    """Write a nerfstudio ``transforms.json`` with one frame per sensor (per-frame intrinsics)."""
    p = Path(path)
    if p.suffix != ".json":
        p = p / "transforms.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    frames = []
    refit = []
    for s in cal.sensors:
        i = s.intrinsics
        c2w = s.pose.inverse().matrix @ _GL_FROM_CV
        k1, k2, p1, p2, k3 = i.dist[:5]
        if i.is_rational:
            (k1, k2, k3), worst, p95 = fit_radial(i, 3)
            refit.append(f"{s.name} (error p95 {p95:.1f} px, corners {worst:.1f} px)")
        frames.append(
            {
                "file_path": f"{image_dir}/{image_name(s)}",
                "transform_matrix": c2w.tolist(),
                "camera_model": "OPENCV",
                "fl_x": i.fx_px,
                "fl_y": i.fy_px,
                "cx": i.cx_px + PIXEL_CENTRE_SHIFT_PX,
                "cy": i.cy_px + PIXEL_CENTRE_SHIFT_PX,
                "w": i.width_px,
                "h": i.height_px,
                "k1": k1,
                "k2": k2,
                "k3": k3,
                "k4": 0.0,
                "p1": p1,
                "p2": p2,
                "egosurg_sensor": s.name,
            }
        )
    doc = {
        "camera_model": "OPENCV",
        "egosurg": {
            "format": "egosurg-rig-calibration-nerfstudio",
            "format_version": EXPORT_FORMAT_VERSION,
            "resolution": cal.resolution.value,
            "world_frame": cal.world_frame,
            "conventions": (
                "metres, world z up; transform_matrix is camera-to-world with nerfstudio/OpenGL "
                "camera axes (x right, y up, z back = OpenCV y and z negated); cx, cy with pixel "
                "(0.5, 0.5) at the centre of the top-left pixel; distortion OpenCV k1 k2 k3 p1 p2"
            ),
        },
        "frames": frames,
    }
    if refit:
        log.warning(
            "nerfstudio's OPENCV model has no rational terms: refitted k1 k2 k3 for %s. For exact "
            "geometry undistort the images first, or use the COLMAP FULL_OPENCV export",
            ", ".join(refit),
        )
    p.write_text(json.dumps(doc, indent=2) + "\n")
    return p


def read_nerfstudio(path: Path | str) -> RigCalibration:
    """Read a ``transforms.json`` whose frames name ``SN<serial>_<side>`` images."""
    p = Path(path)
    if p.is_dir():
        p = p / "transforms.json"
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise CalibrationFileError(f"{p}: no such transforms.json") from None
    except json.JSONDecodeError as exc:
        raise CalibrationFileError(f"{p}: not valid JSON: {exc}") from None
    model = doc.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE"):
        raise CalibrationFileError(f"{p}: camera_model {model!r} cannot be read (OPENCV only)")
    sensors = []
    for k, fr in enumerate(doc.get("frames", [])):
        where = f"{p} frames[{k}]"

        def val(key: str, default: float | None = None, fr: dict = fr, where: str = where) -> float:
            v = fr.get(key, doc.get(key, default))
            if v is None:
                raise CalibrationFileError(f"{where}: missing {key!r}")
            return float(v)

        if val("k4", 0.0) != 0.0:
            raise CalibrationFileError(f"{where}: k4 != 0 cannot be expressed in OpenCV's model")
        serial, side = _parse_name(str(fr.get("file_path", "")), where)
        intr = Intrinsics(
            width_px=int(val("w")),
            height_px=int(val("h")),
            fx_px=val("fl_x"),
            fy_px=val("fl_y"),
            cx_px=val("cx") - PIXEL_CENTRE_SHIFT_PX,
            cy_px=val("cy") - PIXEL_CENTRE_SHIFT_PX,
            dist=(val("k1", 0.0), val("k2", 0.0), val("p1", 0.0), val("p2", 0.0), val("k3", 0.0)),
        )
        c2w = np.asarray(fr.get("transform_matrix"), dtype=np.float64)
        if c2w.shape not in ((4, 4), (3, 4)):
            raise CalibrationFileError(f"{where}: transform_matrix must be 4x4")
        c2w_cv = c2w[:3, :3] @ _GL_FROM_CV[:3, :3]
        R = c2w_cv.T
        t = -R @ c2w[:3, 3]
        sensors.append(_sensor(f"SN{serial}-{side}", serial, side, intr, R, t, where))
    if not sensors:
        raise CalibrationFileError(f"{p}: no frames")
    meta = doc.get("egosurg", {})
    return RigCalibration(
        sensors=tuple(sensors),
        resolution=Resolution.parse(meta["resolution"]) if "resolution" in meta else _res(sensors),
        world_frame=str(meta.get("world_frame", "floor")),
    )


# -- helpers ------------------------------------------------------------------------------------
def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion (w, x, y, z), Hamilton convention, w >= 0."""
    m = np.asarray(R, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    # Shepperd: divide by the largest of the four candidates to stay accurate near 180 degrees
    cand = [tr, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(cand))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    qa = np.asarray(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[0] < 0 else qa


def _sensor(
    name: str, serial: int, side: str, intr: Intrinsics, R: Any, t: Any, where: str
) -> SensorCalibration:
    try:
        pose = Pose(R=np.asarray(R, dtype=np.float64), t_m=np.asarray(t, dtype=np.float64))
    except ValueError as exc:
        raise CalibrationFileError(f"{where}: {exc}") from None
    return SensorCalibration(name=name, camera_serial=serial, side=side, intrinsics=intr, pose=pose)


def _parse_name(name: str, where: str) -> tuple[int, str]:
    m = _NAME_RE.search(name)
    if not m:
        raise CalibrationFileError(
            f"{where}: image name {name!r} does not say which sensor it is (SN<serial>_<side>)"
        )
    return int(m.group(1)), m.group(2)


def _egosurg_header(lines: list[str]) -> dict[str, str]:
    for line in lines:
        if line.startswith("# egosurg:"):
            return dict(kv.split("=", 1) for kv in line[len("# egosurg:") :].split() if "=" in kv)
    return {}


def _res(sensors: list[SensorCalibration]) -> Resolution:
    """The capture mode whose image size the sensors have (HD1200 if none matches)."""
    size = (sensors[0].intrinsics.width_px, sensors[0].intrinsics.height_px)
    for r in Resolution:
        if r.size == size:
            return r
    log.warning("image size %dx%d is no ZED X mode; calling it HD1200", *size)
    return Resolution.HD1200
