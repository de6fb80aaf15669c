"""``sterile``'s real-camera evidence of each contact: what the rig really saw, beside the render.

**Which camera.** Of the rig's left sensors (the case's ``calibration.toml``), those whose image
holds the contact point (in front of the sensor, projected at least ``EDGE_MARGIN`` of the
image inside its border). Among them the one the event's render judged least occluded (the
rig's cameras are among the render's candidate viewpoints, ``sterile_run.best_viewpoint``),
then the nearest along a straight look: the distance over the cosine of the angle between the
sensor's axis and its ray to the contact (a touch at the image's edge is seen obliquely).

**What is written.** ``event_<k>_camera.png``: that sensor's left image at the set nearest the
event's peak, the field box's 12 edges projected through the calibration (with its
distortion, so an edge is drawn as the curve it is in the image), the touching role's points
in red with the contact circled, the role named above their eye, and the time of day and case
burned in; beside it, the same frame enlarged around the touch (about ``2 * ZOOM_HALF_M``
across: a rig camera sees the whole room, so a hand is a few dozen pixels).
``event_<k>_clip.mp4``: the same sensor's frames of every set from 1 s before the event's start
to 1 s after its end, at the session's set rate, the box outlined on every frame and the
frames inside the event marked ``CONTACT`` with a red border; a span longer than
``MAX_CLIP_S`` keeps every n-th set (the frames say so), so a clip plays at most that long.

The frames come through ``RealCameras`` (what ``replay --pip`` reads): a sealed session needs
its identity, and a frame whose checksum fails is shown as damaged, never as the changed
image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Camera
from protocol.formats.site import SiteBox
from reconstructor.replay.clock import CaseClock
from reconstructor.replay.run import RealCameras
from reconstructor.replay.sterile import Event
from reconstructor.replay.sterile_pictures import event_span
from reconstructor.replay.video import Mp4Writer, burn_text, timecode

log = logging.getLogger(__name__)
EDGE_MARGIN = 0.05  # of the image's width and height: a contact at the very border is cut off
CLIP_PAD_S = 1.0  # the clip starts this long before the event and ends this long after it
MAX_CLIP_S = 4.0  # a clip plays at most this long; a longer span keeps every n-th set
MAX_CLIP_FPS = 15.0  # a faster session is decimated to this
BOX_RGB = (255, 210, 0)  # the field box: the renders' yellow
TOUCH_RGB = (255, 40, 40)
EDGE_SAMPLES = 24  # points along each box edge: a distorted edge is a curve
ZOOM_HALF_M = 0.6  # the zoom panel shows about 1.2 m around the touch: hand, arm, drape edge


def zoom_window(
    camera: Camera, contact_m: np.ndarray, size_px: tuple[int, int], scale: float
) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): about ``2 * ZOOM_HALF_M`` around the contact, shaped as the zoom
    panel (half the image's width, its full height), inside the image."""
    w, h = size_px
    px, z = camera.project(np.asarray(contact_m, float)[None])
    u, v = px[0] * scale
    half_h = camera.intrinsics.fy_px * scale * ZOOM_HALF_M / max(float(z[0]), 0.1)
    half_h = float(np.clip(half_h, h / 6, h / 2))  # at most 3x: more shows only pixels
    half_w = min(half_h * (w // 2) / h, w / 2)
    x0 = int(np.clip(u - half_w, 0, w - 2 * half_w))
    y0 = int(np.clip(v - half_h, 0, h - 2 * half_h))
    return x0, y0, x0 + int(2 * half_w), y0 + int(2 * half_h)


def with_zoom(
    rgb: np.ndarray, zoom: np.ndarray, window: tuple[int, int, int, int], lines: list[str],
    ring_px: np.ndarray | None,
) -> np.ndarray:  # fmt: skip
    """(H, W + W/2, 3): ``rgb`` with ``lines`` burned in and the window outlined in white,
    beside ``zoom``'s window (the frame with the box alone, thin) enlarged to (H, W/2), a ring
    around ``ring_px`` (the contact, in the frame's pixels) when given."""
    h, w = rgb.shape[:2]
    x0, y0, x1, y1 = window
    pw = w // 2 - (w // 2) % 2
    panel = cv2.resize(zoom[y0:y1, x0:x1], (pw, h), interpolation=cv2.INTER_CUBIC)
    factor = h / max(y1 - y0, 1)
    if ring_px is not None:
        centre = (int((ring_px[0] - x0) * factor), int((ring_px[1] - y0) * factor))
        cv2.circle(panel, centre, int(h / 8), TOUCH_RGB, 2, cv2.LINE_AA)
    panel = burn_text(panel, [f"x{factor:.1f}: around the touch"])
    full = burn_text(rgb, lines)
    cv2.rectangle(full, (x0, y0), (x1 - 1, y1 - 1), (255, 255, 255), 1, cv2.LINE_AA)
    cv2.line(panel, (0, 0), (0, h - 1), (255, 255, 255), 2)
    return np.concatenate([full, panel], axis=1)


@dataclass(frozen=True)
class CameraEvidence:
    camera: str  # the sensor's name in the calibration
    still: Path
    still_t_s: float  # case time of the set shown
    clip: Path | None  # None: the session holds no set in the clip's span
    clip_from_s: float  # case times of the clip's first and last sets
    clip_to_s: float
    clip_frames: int


def box_edges_m(box: SiteBox, samples: int = EDGE_SAMPLES) -> np.ndarray:
    """(12, samples, 3) world points along each of the box's 12 edges."""
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / 2
    corners = (c * np.asarray(box.size_m)) @ box.rotation.T + np.asarray(box.centre_m)
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    s = np.linspace(0.0, 1.0, samples)[None, :, None]
    a = corners[[p[0] for p in pairs]][:, None]
    b = corners[[p[1] for p in pairs]][:, None]
    return a + s * (b - a)


def _pixels(camera: Camera, points_m: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) pixels in an image ``scale`` times the calibration's, (N,) usable): in front of
    the sensor and near its image (far outside it the distortion model folds back)."""
    px, z = camera.project(points_m)
    k = camera.intrinsics
    w, h = k.width_px, k.height_px
    near = (px[:, 0] > -0.5 * w) & (px[:, 0] < 1.5 * w) & (px[:, 1] > -0.5 * h)
    return px * scale, (z > 0.05) & near & (px[:, 1] < 1.5 * h)


def draw_box(
    rgb: np.ndarray, camera: Camera, box: SiteBox, scale: float = 1.0, thickness_px: int = 2
) -> None:
    """The box's 12 edges, as the calibrated sensor sees them, drawn on ``rgb`` in place."""
    edges = box_edges_m(box)
    for edge in edges:
        px, ok = _pixels(camera, edge, scale)
        ip = np.round(px).astype(int)
        for i in range(len(edge) - 1):
            if ok[i] and ok[i + 1]:
                p, q = (int(ip[i, 0]), int(ip[i, 1])), (int(ip[i + 1, 0]), int(ip[i + 1, 1]))
                cv2.line(rgb, p, q, BOX_RGB, thickness_px, cv2.LINE_AA)


def _view_score(camera: Camera, point_m: np.ndarray) -> float | None:
    """Distance over the cosine of the off-axis angle; None when the point is not well inside
    the image or is behind the sensor."""
    px, z = camera.project(point_m[None])
    k = camera.intrinsics
    u, v = px[0]
    mu, mv = EDGE_MARGIN * k.width_px, EDGE_MARGIN * k.height_px
    if z[0] <= 0.05 or not (mu <= u <= k.width_px - mu and mv <= v <= k.height_px - mv):
        return None
    ray = point_m - camera.pose.centre_m
    dist = float(np.linalg.norm(ray))
    cos = float(z[0]) / dist  # the camera's z axis is its optical axis
    return dist / max(cos, 1e-3)


def best_camera(sensors, contact_m: np.ndarray, unoccluded: dict[str, float]):
    """The sensor that saw ``contact_m`` best (module docstring), or None when no sensor's image
    holds it. ``unoccluded``: the render's visible fraction of the contact per sensor name."""
    best = None
    for s in sensors:
        score = _view_score(s.camera, np.asarray(contact_m, float))
        if score is None:
            continue
        key = (-round(unoccluded.get(s.name, 0.0), 1), score)
        if best is None or key < best[0]:
            best = (key, s)
    return None if best is None else best[1]


def _mark_touch(rgb: np.ndarray, camera: Camera, blob, scale: float) -> None:
    """The role's points (``blob``: its part of the moving things) in red, the contact (its
    in-field points' mean) circled and labelled (the role's name is at its eye)."""
    px, ok = _pixels(camera, blob.points_m, scale)
    for u, v in px[ok]:
        cv2.circle(rgb, (int(u), int(v)), 2, TOUCH_RGB, -1, cv2.LINE_AA)
    px, ok = _pixels(camera, blob.contact_m[None], scale)
    if ok[0]:
        u, v = int(px[0, 0]), int(px[0, 1])
        cv2.circle(rgb, (u, v), 14, TOUCH_RGB, 2, cv2.LINE_AA)
        _label(rgb, "touch", (u + 18, v + 20))


def _label(rgb: np.ndarray, text: str, at: tuple[int, int]) -> None:
    """Red text with a black outline: readable on a drape, a gown or the floor."""
    for colour, thick in (((0, 0, 0), 4), (TOUCH_RGB, 2)):
        cv2.putText(rgb, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, thick, cv2.LINE_AA)


def _even(rgb: np.ndarray) -> np.ndarray:
    """Cropped to an even width and height (H.264's yuv420p)."""
    h, w = rgb.shape[:2]
    return np.ascontiguousarray(rgb[: h - h % 2, : w - w % 2])


def clip_times(set_t_s: np.ndarray, start_s: float, end_s: float) -> tuple[list[float], int, float]:
    """(the clip's set times, every how many sets, its frame rate): the sets from
    ``start_s - CLIP_PAD_S`` to ``end_s + CLIP_PAD_S`` at the session's set rate (at most
    ``MAX_CLIP_FPS``), every n-th of them when more would play longer than ``MAX_CLIP_S``."""
    lo, hi = start_s - CLIP_PAD_S - 1e-6, end_s + CLIP_PAD_S + 1e-6
    chosen = np.nonzero((set_t_s >= lo) & (set_t_s <= hi))[0]
    rate = 1.0 / max(float(np.median(np.diff(set_t_s))), 1e-3) if len(set_t_s) > 1 else 1.0
    base = max(1, int(np.ceil(rate / MAX_CLIP_FPS - 1e-6)))  # real time, at most that rate
    fps = rate / base
    step = base * max(1, int(np.ceil(len(chosen) / base / (MAX_CLIP_S * fps))))
    return [float(set_t_s[k]) for k in chosen[::step]], step, fps


def camera_evidence(
    out: Path, number: int, event: Event, box: SiteBox, real: RealCameras, clock: CaseClock,
    unoccluded: dict[str, float], role_eye=None,
) -> CameraEvidence | None:  # fmt: skip
    """Event ``number``'s still and clip (module docstring); None when no camera saw it.
    ``role_eye``: case time -> the touching role's eye (its name is drawn there), or None."""
    blob, inst = event.blobs[event.peak], event.instants[event.peak]
    sensor = best_camera(real.sensors, blob.contact_m, unoccluded)
    if sensor is None:
        log.warning("event %d: no rig camera's image holds the contact; no camera still", number)
        return None
    who = event.role or "unknown role"
    span = event_span(clock, event.start_s, event.end_s)

    k_px = sensor.intrinsics
    window: tuple[int, int, int, int] | None = None

    def picture(t_s: float, lines: list[str], touch) -> tuple[np.ndarray, float]:
        nonlocal window
        image, label = real.sensor_frame(sensor, t_s)
        set_t = float(real.set_t_s[int(np.argmin(np.abs(real.set_t_s - t_s)))])
        if image is None:  # the camera has no frame in that set: grey, saying so
            image = burn_text(np.full((k_px.height_px, k_px.width_px, 3), 40, np.uint8), [label])
        rgb, zoom = np.array(image, copy=True), np.array(image, copy=True)
        scale = rgb.shape[1] / k_px.width_px
        draw_box(rgb, sensor.camera, box, scale)
        draw_box(zoom, sensor.camera, box, scale, thickness_px=1)  # the hand stays visible
        if touch is not None:
            _mark_touch(rgb, sensor.camera, touch, scale)
        if role_eye is not None:
            _name_at(rgb, sensor.camera, role_eye(set_t), who, scale)
        if window is None:  # one window for the still and the whole clip
            window = zoom_window(sensor.camera, blob.contact_m, rgb.shape[1::-1], scale)
        when = clock.time_of_day(set_t) or timecode(set_t)
        stamp = [clock.stamp(set_t), f"{sensor.name} at {when}", *lines]
        ring = _pixels(sensor.camera, touch.contact_m[None], scale)[0][0] if touch else None
        return with_zoom(rgb, zoom, window, stamp, ring), set_t

    title = f"event {number}: {who} in {event.field}, {span}"
    still, still_t = picture(inst.t_s, [title, "field box in yellow, the touch in red"], blob)
    still_path = out / f"event_{number:03d}_camera.png"
    cv2.imwrite(str(still_path), np.ascontiguousarray(still[:, :, ::-1]))

    times, step, fps = clip_times(real.set_t_s, event.start_s, event.end_s)
    size = _even(still).shape[1::-1]

    def clip_frame(t: float) -> np.ndarray:
        inside = event.start_s - 1e-6 <= t <= event.end_s + 1e-6
        near = int(np.argmin([abs(i.t_s - t) for i in event.instants]))
        when = "CONTACT" if inside else "before" if t < event.start_s else "after"
        every = f" (every {step}th set)" if step > 1 else ""
        rgb, _ = picture(t, [title, when + every], event.blobs[near] if inside else None)
        if inside:
            cv2.rectangle(rgb, (0, 0), (rgb.shape[1] - 1, rgb.shape[0] - 1), TOUCH_RGB, 6)
        rgb = _even(rgb)
        if rgb.shape[1::-1] != size:
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        return rgb

    clip_path = out / f"event_{number:03d}_clip.mp4" if times else None
    if clip_path is None:
        log.warning("event %d: the session has no set from 1 s before to 1 s after it; no clip",
                    number)  # fmt: skip
    else:
        with Mp4Writer(clip_path, size, fps) as video:
            for t in times:
                video.write(clip_frame(t))
    return CameraEvidence(
        camera=sensor.name, still=still_path, still_t_s=still_t, clip=clip_path,
        clip_from_s=times[0] if times else float("nan"),
        clip_to_s=times[-1] if times else float("nan"), clip_frames=len(times),
    )  # fmt: skip


def _name_at(rgb: np.ndarray, camera: Camera, eye_m: np.ndarray | None, who: str,
             scale: float) -> None:  # fmt: skip
    """The role's name above its eye, where the sensor sees that eye."""
    if eye_m is None:
        return
    px, ok = _pixels(camera, np.asarray(eye_m, float)[None], scale)
    if ok[0]:
        u, v = int(px[0, 0]), int(px[0, 1])
        cv2.drawMarker(rgb, (u, v), TOUCH_RGB, cv2.MARKER_TRIANGLE_DOWN, 16, 2, cv2.LINE_AA)
        _label(rgb, who, (u - 30, v - 14))
