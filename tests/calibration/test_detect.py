"""Wand-sphere detection and labelling, against the simulator's truth.

Frames come from ``World.from_seed(5, phase="wand")``, unit 2 (it sees the wand lying on the
floor too), at HD1200, with sensor noise; the background is the median of frames at other times.
The waved frames are picked from the sim's truth along the operator's tour (``_waved``), not
fixed times, so they stay valid when the tour changes. ``object_index`` is used only to decide
which spheres are fully visible, never by the code under test. Numbers worth knowing are printed
(run with ``-s``).
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from calibration.detect.config import DetectorConfig, SphereBlob
from calibration.detect.detector import SphereDetector
from calibration.detect.label import (
    AMBIGUOUS,
    FEWER_THAN_3,
    NOT_COLLINEAR,
    NOT_IN_BOTH_VIEWS,
    RATIO_MISMATCH,
    WAND_MISMATCH,
    LabelResult,
    RejectionCounter,
    StereoConfig,
    label_stereo,
    label_wand,
    refit_without_rod,
)
from calibration.detect.sphere_geometry import (
    cone_axis_from_conic,
    conic_of_sphere,
    eccentricity_bias_px,
    fit_sphere_outline,
    project_directions,
)
from protocol.camera import Camera, Intrinsics, Pose
from protocol.formats.wand import WandSpec
from sim.render import SPHERE_OBJECT_BASE, FrameScene, Spheres, render_view
from sim.sensor import SensorSpec, expose
from sim.truth import (
    wand_axis_angle_deg,
    wand_in_clear_view,
    wand_sphere_camouflaged,
    wand_sphere_whole,
)
from sim.wand_tour import MAX_RANGE_M
from sim.world import WAND_SPHERE_ALBEDO

UNIT = 2
FLOOR_T = 1.25  # the wand still lies on the floor
# waved frames: every sphere whole in both views (clear of the operator's hand and of each other),
# in front of the room's own colours (not of an orange patch, where colour shows no outline),
# within the range the tour plans for (farther, a 40 mm sphere is 2-3 px in radius and its size
# says little about its distance), not pointing at the camera; at least 1 s apart on the tour
N_WAVED = 5
WAVED_STEP_S = 0.25
WAVED_SPACING_S = 1.0
MIN_AXIS_ANGLE_DEG = 45.0
N_BACKGROUND = 7  # spread evenly over the tour's loop
SIDES = ("left", "right")
WAND = WandSpec()


def _bgr(render) -> np.ndarray:
    return np.ascontiguousarray(render.image_rgb[:, :, ::-1])


def _tour_span_s(world) -> tuple[float, float]:
    """(start, period) of the operator's tour: from the pick-up's end, once round its loop."""
    motion = world.wand_motion
    assert motion.tour is not None, "the wand world's operator should follow the coverage tour"
    return motion.floor_lie_s + motion.pickup_s, float(motion.tour.arrive_s[-1])


def _waved(world, cams) -> tuple[tuple[float, ...], dict]:
    """The first ``N_WAVED`` times along the tour, ``WAVED_SPACING_S`` apart, that meet the
    criteria above in both views, and their renders: the geometry picks the candidates
    (``wand_in_clear_view``), a render confirms that nothing hides a sphere or blends with it."""
    start, period = _tour_span_s(world)
    times: list[float] = []
    renders: dict[tuple[str, float], object] = {}
    for t in np.arange(start, start + period, WAVED_STEP_S):
        t = round(float(t), 3)
        if times and t - times[-1] < WAVED_SPACING_S:
            continue
        if not all(
            wand_in_clear_view(
                world, cam, t, max_range_m=MAX_RANGE_M, min_axis_angle_deg=MIN_AXIS_ANGLE_DEG
            )
            for cam in cams.values()
        ):
            continue
        views = {side: world.render_sensor(UNIT, side, t) for side in SIDES}
        if all(
            wand_sphere_whole(world, views[s], t, k)
            and not wand_sphere_camouflaged(world, views[s], t, k)
            for s in SIDES
            for k in range(3)
        ):
            times.append(t)
            renders.update({(side, t): r for side, r in views.items()})
            if len(times) == N_WAVED:
                return tuple(times), renders
    raise AssertionError(f"the tour shows unit {UNIT} the wand whole at only {times}")


def _off_centre_px(cam: Camera, world, t: float) -> float:
    """How far the wand's middle sphere is from the principal point in ``cam``'s image."""
    px, _ = cam.project(world.wand_centres(t)[1:2])
    return float(np.hypot(px[0, 0] - cam.intrinsics.cx_px, px[0, 1] - cam.intrinsics.cy_px))


def _background_times(world) -> tuple[float, ...]:
    start, period = _tour_span_s(world)
    return tuple(round(start + period * (i + 0.5) / N_BACKGROUND, 3) for i in range(N_BACKGROUND))


def _assert_median_is_the_room(world, renders: list) -> None:
    """The temporal median shows the room where fewer than half the frames show something that
    moves (the wand, its operator): the background the detector needs, checked on the truth."""
    moving = sum((r.object_index >= len(world.static_objects)).astype(int) for r in renders)
    assert moving.max() < len(renders) / 2, "pick background times where the operator is apart"


@pytest.fixture(scope="module")
def sim(wand_world):
    """Rendered frames, fitted detectors and their detections, shared by the tests below."""
    world = wand_world
    unit = world.rig[UNIT]
    cams = {side: unit.sensor(side, "HD1200") for side in SIDES}
    renders: dict[str, list] = {side: [] for side in SIDES}
    for t in _background_times(world):
        for side in SIDES:  # both sides at one time share the scene's ray-casting structure
            renders[side].append(world.render_sensor(UNIT, side, t))
    backgrounds: dict[str, list[np.ndarray]] = {}
    for side in SIDES:
        _assert_median_is_the_room(world, renders[side])
        backgrounds[side] = [_bgr(r) for r in renders[side]]
    detectors = {}
    for side in SIDES:
        det = SphereDetector(cams[side].intrinsics, WAND.radius_m)
        det.fit_background(backgrounds[side])
        detectors[side] = det
    waved_t, waved_renders = _waved(world, cams)
    frames, blobs, times_ms = {}, {}, []
    for t in (FLOOR_T, *waved_t):
        for side in SIDES:
            r = waved_renders.get((side, t)) or world.render_sensor(UNIT, side, t)
            img = _bgr(r)
            detectors[side].detect(img)  # warm caches; time the second call
            t0 = time.perf_counter()
            found = detectors[side].detect(img)
            times_ms.append(1000 * (time.perf_counter() - t0))
            frames[(side, t)] = r
            blobs[(side, t)] = found
    return SimpleNamespace(
        world=world,
        unit=unit,
        cams=cams,
        detectors=detectors,
        backgrounds=backgrounds,
        waved_t=waved_t,
        # the waved frame where the wand lies most nearly across the left view
        across_t=max(waved_t, key=lambda t: wand_axis_angle_deg(world, cams["left"], t)),
        # ... and where it is nearest the left image's centre, where a sphere's image is round
        # (so a flat disc drawn there looks like one)
        central_t=min(waved_t, key=lambda t: _off_centre_px(cams["left"], world, t)),
        frames=frames,
        blobs=blobs,
        times_ms=times_ms,
        stereo=unit.factory.stereo("HD1200"),
    )


def _truth(sim, side: str, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected true centres (3, 2), their depths z (3,) and distances (3,) from the sensor."""
    cam = sim.cams[side]
    centres = sim.world.wand_centres(t)
    px, z = cam.project(centres)
    return px, z, np.linalg.norm(cam.pose.transform(centres), axis=1)


def _nearest(blobs: list[SphereBlob], p: np.ndarray) -> tuple[SphereBlob | None, float]:
    if not blobs:
        return None, math.inf
    d = [float(np.hypot(*(np.asarray(b.centre_px) - p))) for b in blobs]
    i = int(np.argmin(d))
    return blobs[i], d[i]


# ---- the geometry, exactly ---------------------------------------------------------------------


def _silhouette_px(cam: Camera, centre_cam: np.ndarray, radius_m: float, n: int = 90):
    """Exact outline of a sphere (camera frame) through the lens, in distorted pixels."""
    D = float(np.linalg.norm(centre_cam))
    a = centre_cam / D
    alpha = math.asin(radius_m / D)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = np.linspace(0, 2 * math.pi, n, endpoint=False)
    rays = math.cos(alpha) * a + math.sin(alpha) * (
        np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    )
    return project_directions(rays, cam.intrinsics), a, math.sin(alpha)


def test_cone_axis_recovers_the_centre_exactly_where_the_ellipse_centre_is_biased(wand_world):
    """A 40 mm sphere 1 m away, 50 degrees off axis, through a real (distorted) ZED X lens."""
    lens = wand_world.rig[0].sensor("left", "HD1200").intrinsics
    pinhole = lens.undistorted()
    theta = math.radians(50.0)
    centre = 1.0 * np.array([math.sin(theta), 0.0, math.cos(theta)])
    for intr in (pinhole, lens):
        cam = Camera(name="c", intrinsics=intr, pose=Pose(R=np.eye(3)))
        edge_px, axis, sin_alpha = _silhouette_px(cam, centre, 0.02)
        truth_px, _ = cam.project(centre[None])
        fit = fit_sphere_outline(edge_px, intr, 0.02)
        assert np.abs(fit.centre_px - truth_px[0]).max() < 1e-6
        assert fit.distance_m == pytest.approx(1.0, abs=1e-9)
        assert np.abs(fit.residuals_px).max() < 1e-6
        bias = float(np.linalg.norm(fit.ellipse_centre_px - truth_px[0]))
        expected = eccentricity_bias_px(intr.fx_px, theta, 0.02)
        print(f"ellipse-centre bias at 50 deg, 1 m: {bias:.3f} px (pinhole formula {expected:.3f})")
        if intr is pinhole:  # eccentricity_bias_px holds exactly for a pinhole
            assert bias == pytest.approx(expected, rel=1e-6)
        else:  # barrel distortion shrinks it a little, but it stays large
            assert 0.7 * expected < bias < expected
        # the general conic route: eigenvector of the distinct eigenvalue
        a, s = cone_axis_from_conic(conic_of_sphere(axis, sin_alpha))
        assert np.allclose(a, axis, atol=1e-12) and s == pytest.approx(sin_alpha, rel=1e-12)
        fit_c = fit_sphere_outline(edge_px, intr, 0.02, method="conic")
        assert np.abs(fit_c.centre_px - truth_px[0]).max() < 1e-4
    with pytest.raises(ValueError, match="real cone"):
        cone_axis_from_conic(np.eye(3))  # x^2 + y^2 + 1 = 0 has no real points


def test_bias_correction_matters_towards_the_image_edge(wand_world):
    """Spheres rendered by the sim 1 m from a wall camera, from the image centre to 50 degrees
    off axis: the ellipse centre drifts outward with the angle, the cone axis does not."""
    world = wand_world
    cam = world.rig[0].sensor("left", "HD1200")
    thetas = (0.0, 20.0, 35.0, 45.0, 50.0)
    centres = []
    for i, th in enumerate(thetas):
        side = 1.0 if i % 2 == 0 else -1.0
        d = np.array(
            [side * math.sin(math.radians(th)), 0.045 * (i - 2), math.cos(math.radians(th))]
        )
        centres.append(cam.pose.centre_m + cam.pose.R.T @ (d / np.linalg.norm(d)))
    centres_w = np.array(centres)
    scene = FrameScene(
        list(world.static_objects),
        world.lights,
        world.textures,
        Spheres(centres_w, WAND.radius_m, WAND_SPHERE_ALBEDO),
    )
    image = expose(render_view(scene, cam).radiance, cam.intrinsics, SensorSpec(), 1234)
    det = SphereDetector(cam.intrinsics, WAND.radius_m)
    blobs = det.detect(np.ascontiguousarray(image[:, :, ::-1]))
    truth, _ = cam.project(centres_w)
    corrected, uncorrected = [], []
    for k, th in enumerate(thetas):
        blob, err = _nearest(blobs, truth[k])
        assert blob is not None and err < 1.0, f"sphere at {th} deg not found"
        corrected.append(err)
        uncorrected.append(float(np.hypot(*(np.asarray(blob.ellipse_centre_px) - truth[k]))))
        assert blob.distance_m == pytest.approx(1.0, rel=0.005)
    print("angle (deg)        ", thetas)
    print("ellipse centre (px)", np.round(uncorrected, 3))
    print("cone axis (px)     ", np.round(corrected, 3))
    assert max(corrected) < 0.05
    assert uncorrected[-1] > 0.6 and uncorrected[-2] > 0.4
    assert all(np.diff(uncorrected) > 0)  # grows towards the edge
    assert max(corrected) < 0.1 * uncorrected[-1]


# ---- detection on sim frames -----------------------------------------------------------------


def test_detected_centres_match_the_projected_true_centres(sim):
    errors, ellipse_errors, dist_errors = [], [], []
    floor_checked = 0
    for (side, t), render in sim.frames.items():
        truth, _, dist = _truth(sim, side, t)
        for k in range(3):
            if not wand_sphere_whole(sim.world, render, t, k):
                continue
            blob, err = _nearest(sim.blobs[(side, t)], truth[k])
            assert blob is not None and err < 1.0, f"missed sphere {k} ({side}, t={t})"
            errors.append(err)
            ellipse_errors.append(float(np.hypot(*(np.asarray(blob.ellipse_centre_px) - truth[k]))))
            dist_errors.append(abs(blob.distance_m / dist[k] - 1))
            floor_checked += t == FLOOR_T
    errors_a = np.array(errors)
    print(
        f"\n{len(errors)} fully visible spheres: centre error median {np.median(errors_a):.3f} px, "
        f"p90 {np.percentile(errors_a, 90):.3f}, max {errors_a.max():.3f}; "
        f"uncorrected ellipse centre median {np.median(ellipse_errors):.3f}, "
        f"max {max(ellipse_errors):.3f}; distance error median {100 * np.median(dist_errors):.2f}%"
        f", max {100 * max(dist_errors):.2f}%"
    )
    print(
        f"detection time per HD1200 frame: median {np.median(sim.times_ms):.1f} ms, "
        f"max {max(sim.times_ms):.1f} ms"
    )
    assert len(errors) >= 20 and floor_checked >= 3
    assert np.median(errors_a) < 0.1
    assert errors_a.max() < 0.3
    assert max(dist_errors) < 0.03


def test_numba_kernels_give_the_numpy_twins_results(sim):
    """What calibration runs per frame (detect, label, refit without the rod), with the numba
    kernels (the default) and with their numpy twins: the same spheres and labels, the centres
    within 1e-5 px. How much faster the kernels are is measured by bench/bench_wand_detect.py
    (BENCHMARKS.md), not asserted here."""
    twins = {}
    for side in SIDES:
        twins[side] = SphereDetector(
            sim.cams[side].intrinsics, WAND.radius_m, DetectorConfig(kernels="numpy")
        )
        twins[side].fit_background(sim.backgrounds[side])
    labelled = 0
    for (side, _t), render in sim.frames.items():
        img = _bgr(render)
        runs = {}
        for det in (sim.detectors[side], twins[side]):
            blobs = det.detect(img)
            runs[det.config.kernels] = (blobs, refit_without_rod(det, img, label_wand(blobs, WAND)))
        (fast_blobs, fast), (slow_blobs, slow) = runs["numba"], runs["numpy"]
        assert len(fast_blobs) == len(slow_blobs)
        for a, b in zip(fast_blobs, slow_blobs, strict=True):
            assert np.abs(np.subtract(a.centre_px, b.centre_px)).max() < 1e-5
            assert a.n_edge_points == b.n_edge_points
        assert fast.ok == slow.ok and fast.reason == slow.reason
        if fast.points_px is not None and slow.points_px is not None:
            assert np.abs(fast.points_px - slow.points_px).max() < 1e-5
            labelled += 1
    assert labelled >= 10


def _jpeg(img: np.ndarray, sampling: int) -> np.ndarray:
    params = [int(cv2.IMWRITE_JPEG_QUALITY), 92, int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR), sampling]
    ok, buf = cv2.imencode(".jpg", img, params)
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    assert ok and out is not None
    return out


def test_jpeg_frames_keep_sub_pixel_accuracy_with_full_chroma(sim):
    """Sessions store JPEG. At quality 92 with 4:4:4 chroma the detector keeps its accuracy;
    with OpenCV's default 4:2:0 the colour of the 3-5 px spheres is stored on a 2x2 grid and the
    centres wander by tenths of a pixel (printed, for the record)."""
    side = "left"
    results = {}
    for name, sampling in (
        ("4:4:4", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
        ("4:2:0", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420),
    ):
        det = SphereDetector(sim.cams[side].intrinsics, WAND.radius_m)
        det.fit_background([_jpeg(b, sampling) for b in sim.backgrounds[side][::2]])
        errors, missed = [], 0
        for t in (FLOOR_T, *sim.waved_t):
            render = sim.frames[(side, t)]
            truth, _, _ = _truth(sim, side, t)
            blobs = det.detect(_jpeg(_bgr(render), sampling))
            for k in range(3):
                if wand_sphere_whole(sim.world, render, t, k):
                    _, err = _nearest(blobs, truth[k])
                    if err < 2.0:
                        errors.append(err)
                    else:
                        missed += 1
        e = np.array(errors)
        results[name] = (e, missed)
        print(
            f"JPEG q92 {name}: {len(e)} spheres, {missed} missed, centre error median "
            f"{np.median(e):.3f} px, max {e.max():.3f} px"
        )
    e, missed = results["4:4:4"]
    assert missed == 0 and len(e) >= 10
    assert np.median(e) < 0.1 and e.max() < 0.3


def test_the_background_keeps_static_orange_clutter_out(sim):
    """The room's orange equipment labels look like spheres to colour alone."""
    side, t = "left", sim.central_t
    img = _bgr(sim.frames[(side, t)])
    truth, _, _ = _truth(sim, side, t)
    bare = SphereDetector(sim.cams[side].intrinsics, WAND.radius_m)
    clutter = [b for b in bare.detect(img) if np.linalg.norm(truth - b.centre_px, axis=1).min() > 2]
    with_bg = sim.blobs[(side, t)]
    assert clutter, "expected colour alone to pick up some clutter in this view"
    assert len(with_bg) == 3
    for b in with_bg:
        assert np.linalg.norm(truth - b.centre_px, axis=1).min() < 0.5


def test_colour_model_can_be_learned_from_sphere_pixels(sim):
    side, t = "left", sim.central_t
    render = sim.frames[(side, t)]
    inner = cv2.erode(
        (render.object_index >= SPHERE_OBJECT_BASE).astype(np.uint8), np.ones((3, 3), np.uint8)
    )
    pixels = _bgr(render)[inner > 0]
    cfg = DetectorConfig.from_sphere_pixels(pixels)
    assert cfg.hue_range[0] <= 16 <= cfg.hue_range[1]
    learned = np.asarray(cfg.sphere_rgb) / np.linalg.norm(cfg.sphere_rgb)
    albedo = np.asarray(WAND_SPHERE_ALBEDO) / np.linalg.norm(WAND_SPHERE_ALBEDO)
    assert float(learned @ albedo) > 0.995
    det = SphereDetector(sim.cams[side].intrinsics, WAND.radius_m, cfg)
    det.fit_background(sim.backgrounds[side])
    truth, _, _ = _truth(sim, side, t)
    found = det.detect(_bgr(render))
    assert len(found) == 3
    assert max(np.linalg.norm(truth - b.centre_px, axis=1).min() for b in found) < 0.3


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="hue_range"):
        DetectorConfig(hue_range=(40, 10))
    with pytest.raises(ValueError, match="centre_method"):
        DetectorConfig(centre_method="centroid")
    intr = Intrinsics.from_fov(640, 400, 90.0)
    det = SphereDetector(intr, 0.02)
    with pytest.raises(ValueError, match="640x400"):
        det.detect(np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        det.detect(np.zeros((400, 640, 3), np.float32))
    with pytest.raises(ValueError, match="at least 3"):
        det.fit_background([np.zeros((400, 640, 3), np.uint8)])
    assert det.detect(np.zeros((400, 640, 3), np.uint8)) == []


# ---- labelling ---------------------------------------------------------------------------------


def test_labels_come_out_in_wand_order_on_sim_frames(sim):
    labelled = 0
    for (side, t), blobs in sim.blobs.items():
        truth, _, _ = _truth(sim, side, t)
        res = label_wand(blobs, WAND)
        if res.ok:
            assert res.points_px is not None
            err = np.linalg.norm(res.points_px - truth, axis=1)
            assert err.max() < 0.5, f"wrong order ({side}, t={t}): {err}"
            labelled += 1
            # the wand-implied distances are only as good as the perspective they come from
            # (poor when the wand points along the line of sight), hence the labeller's 15%
            _, _, dist = _truth(sim, side, t)
            assert res.depths_m is not None
            assert np.allclose(res.depths_m, dist, rtol=0.15)
    print(f"labelled {labelled} of {len(sim.blobs)} frames")
    assert labelled >= 10


def _blob(x: float, y: float, distance_m: float = math.nan, score: float = 1.0) -> SphereBlob:
    """A detection at normalized (x, y) of a 740 px pinhole (for labeller-only tests)."""
    px = (960.0 + 740.0 * x, 600.0 + 740.0 * y)
    return SphereBlob(
        centre_px=px,
        ellipse_centre_px=px,
        radius_px=5.0,
        score=score,
        distance_m=distance_m,
        centre_normalized=(x, y),
        focal_px=740.0,
    )


def _wand_blobs(first: np.ndarray, direction: np.ndarray, wand: WandSpec = WAND):
    """Blobs of an exact wand (camera frame), with exact distances."""
    pts = first + np.outer(np.asarray(wand.sphere_positions_mm) / 1000.0, direction)
    return [_blob(p[0] / p[2], p[1] / p[2], float(np.linalg.norm(p))) for p in pts], pts


def test_label_rejections_have_reasons(sim):
    side, t = "left", sim.central_t
    blobs = sim.blobs[(side, t)]
    res = label_wand(blobs[:2], WAND)
    assert not res.ok and res.reason == FEWER_THAN_3
    # the same three detections with the middle one moved 10 px off the line
    good = label_wand(blobs, WAND)
    assert good.ok
    first, mid, last = good.blobs
    along = np.subtract(last.centre_normalized, first.centre_normalized)
    normal = np.array([-along[1], along[0]]) / np.linalg.norm(along)
    nx, ny = np.asarray(mid.centre_normalized) + 10.0 / mid.focal_px * normal
    bent = SphereBlob(
        centre_px=mid.centre_px,
        ellipse_centre_px=mid.ellipse_centre_px,
        radius_px=mid.radius_px,
        score=mid.score,
        distance_m=mid.distance_m,
        centre_normalized=(float(nx), float(ny)),
        focal_px=mid.focal_px,
    )
    assert label_wand([first, bent, last], WAND).reason == NOT_COLLINEAR
    # collinear, but equally spaced: no 1:2 wand looks like that face-on
    even = [_blob(-0.1, 0.0), _blob(0.0, 0.0), _blob(0.1, 0.0)]
    assert label_wand(even, WAND).reason == RATIO_MISMATCH
    # with distances: a 1:2 image ratio whose sizes say the wand is face-on at 3 m is fine...
    wand_blobs, _ = _wand_blobs(np.array([-0.2, 0.1, 3.0]), np.array([1.0, 0.0, 0.0]))
    assert label_wand(wand_blobs, WAND).ok
    # ...but not when the sizes disagree with the perspective that ratio would need
    wrong_size = [
        _blob(b.centre_normalized[0], b.centre_normalized[1], distance_m=d)
        for b, d in zip(wand_blobs, (3.0, 2.0, 3.0), strict=True)
    ]
    assert label_wand(wrong_size, WAND).reason == RATIO_MISMATCH
    # two copies of the same wand, side by side: either could be it
    shifted = [
        _blob(b.centre_normalized[0], b.centre_normalized[1] + 0.2, b.distance_m)
        for b in wand_blobs
    ]
    assert label_wand(wand_blobs + shifted, WAND).reason == AMBIGUOUS


def test_perspective_labelling_survives_a_wand_pointing_at_the_camera():
    """Image ratio far from 1:2, which the plain ratio test would reject; the 3D check labels it."""
    direction = np.array([0.3, 0.1, -1.0])
    blobs, _ = _wand_blobs(np.array([0.1, 0.05, 1.4]), direction / np.linalg.norm(direction))
    xy = np.array([b.centre_normalized for b in blobs])
    ratio = np.linalg.norm(xy[1] - xy[0]) / np.linalg.norm(xy[2] - xy[1])
    assert abs(ratio / 0.5 - 1) > 0.3
    res = label_wand(blobs[::-1], WAND)
    assert res.ok and res.points_px is not None
    assert np.allclose(res.points_px, [b.centre_px for b in blobs])


def test_a_fake_orange_disc_does_not_break_labelling(sim):
    """A sphere-coloured disc near the wand (off its line, then on its line beyond the last
    sphere) is detected like a sphere, and the labeller still picks the wand."""
    side, t = "left", sim.central_t
    render = sim.frames[(side, t)]
    truth, _, _ = _truth(sim, side, t)
    good = label_wand(sim.blobs[(side, t)], WAND)
    assert good.ok
    radius = float(np.mean([b.radius_px for b in good.blobs]))
    inner = cv2.erode(
        (render.object_index == SPHERE_OBJECT_BASE + 1).astype(np.uint8),
        np.ones((3, 3), np.uint8),
    )
    colour = np.median(_bgr(render)[inner > 0], axis=0)
    along = (truth[2] - truth[0]) / np.linalg.norm(truth[2] - truth[0])
    normal = np.array([-along[1], along[0]])
    spacing = float(np.linalg.norm(truth[2] - truth[1]))
    for where in (truth[1] + 6 * radius * normal, truth[2] + 0.4 * spacing * along):
        img = _bgr(render).copy()
        cv2.circle(
            img,
            (round(where[0] * 16), round(where[1] * 16)),
            round(radius * 16),
            tuple(float(c) for c in colour),
            -1,
            cv2.LINE_AA,
            shift=4,
        )
        blobs = sim.detectors[side].detect(img)
        fake, err = _nearest(blobs, where)
        assert fake is not None and err < 1.0, "the fake disc should look like a sphere"
        res = label_wand(blobs, WAND)
        assert res.ok and res.points_px is not None, res.reason
        assert np.linalg.norm(res.points_px - truth, axis=1).max() < 0.5


# ---- stereo ----------------------------------------------------------------------------------


def test_stereo_triangulates_the_wand_and_fixes_a_flipped_view(sim):
    errors = []
    checked = 0
    for t in (FLOOR_T, *sim.waved_t):
        left = label_wand(sim.blobs[("left", t)], WAND)
        right = label_wand(sim.blobs[("right", t)], WAND)
        if not (left.ok and right.ok):
            continue
        res = label_stereo(left, right, sim.stereo, WAND)
        assert res.ok, f"t={t}: {res.reason}"
        assert res.distances_mm is not None and res.points_left_m is not None
        assert not res.flipped_left and not res.flipped_right
        errors.append(np.abs(res.distances_mm - np.asarray(WAND.distances_mm)))
        truth_left = sim.unit.left_pose.transform(sim.world.wand_centres(t))
        point_mm = 1000 * np.linalg.norm(res.points_left_m - truth_left, axis=1)
        print(
            f"t={t}: distances {np.round(res.distances_mm, 1)} mm, points off by "
            f"{np.round(point_mm, 1)} mm at {np.round(truth_left[:, 2], 2)} m"
        )
        # one view labelled backwards: the 3D check relabels it
        fixed = label_stereo(left.flipped(), right, sim.stereo, WAND)
        assert fixed.ok and fixed.flipped_left and not fixed.flipped_right
        assert fixed.left_px is not None and left.points_px is not None
        assert np.allclose(fixed.left_px, left.points_px)
        both = label_stereo(left.flipped(), right.flipped(), sim.stereo, WAND)
        assert both.ok and both.flipped_left and both.flipped_right
        assert both.right_px is not None and right.points_px is not None
        assert np.allclose(both.right_px, right.points_px)
        checked += 1
    err = np.concatenate(errors)
    print(
        f"stereo distance errors over {checked} frames: median {np.median(err):.1f} mm, "
        f"max {err.max():.1f} mm"
    )
    assert checked >= 4
    # depth noise of a 12 cm baseline: 0.1 px of disparity is 14 mm of depth at 3.5 m
    assert np.median(err) < 4.0
    assert err.max() < 15.0


def test_stereo_rejects_a_wand_of_the_wrong_geometry(sim):
    # a frame where the wand lies across the view, so a 50 mm discrepancy is unmistakable
    t = sim.across_t
    left = label_wand(sim.blobs[("left", t)], WAND)
    right = label_wand(sim.blobs[("right", t)], WAND)
    assert left.ok and right.ok
    other = WandSpec(sphere_positions_mm=(0.0, 200.0, 500.0))
    res = label_stereo(left, right, sim.stereo, other)
    assert not res.ok and res.reason == WAND_MISMATCH
    plain = StereoConfig(disparity_sigma_px=0.0)
    assert label_stereo(left, right, sim.stereo, other, plain).reason == WAND_MISMATCH
    assert label_stereo(left, LabelResult.rejected(FEWER_THAN_3), sim.stereo, WAND).reason == (
        NOT_IN_BOTH_VIEWS
    )


def test_rejection_counter_counts_per_reason():
    counter = RejectionCounter()
    counter.update([None, FEWER_THAN_3, LabelResult.rejected(NOT_COLLINEAR), FEWER_THAN_3])
    counter.add(LabelResult(points_px=np.zeros((3, 2))))
    other = RejectionCounter()
    other.add(NOT_COLLINEAR)
    counter.merge(other)
    assert counter.accepted == 2 and counter.total == 6
    assert counter.as_dict() == {FEWER_THAN_3: 2, NOT_COLLINEAR: 2}
