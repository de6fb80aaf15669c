"""The simulator's true rig as a calibration, and how far an estimated calibration is from it.

The calibration a user would get from a perfect wand session is the sim's own camera model: this
module writes it in the product's calibration format (``protocol.formats.rig_calibration``), so the
reconstructor can run on the truth before a wand calibration exists, and a wand calibration can
be scored against it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from protocol.camera import Camera, Pose, Resolution
from protocol.formats.rig_calibration import RigCalibration, SensorCalibration
from sim.render import SPHERE_OBJECT_BASE
from sim.world import Render, World


def true_rig_calibration(
    world: World, resolution: Resolution | str = Resolution.HD1200
) -> RigCalibration:
    """The eight sensors of the sim's four ZED X, with their true intrinsics and poses."""
    res = Resolution.parse(resolution)
    sensors = []
    for unit in world.rig:
        for side in ("left", "right"):
            cam = unit.sensor(side, res)
            sensors.append(
                SensorCalibration(
                    name=cam.name,
                    camera_serial=unit.serial,
                    side=side,
                    intrinsics=cam.intrinsics,
                    pose=cam.pose,
                )
            )
    return RigCalibration(
        sensors=tuple(sensors),
        resolution=res,
        world_frame="floor",
        metadata={"source": f"simulator truth, seed {world.config.seed}"},
    )


@dataclass(frozen=True)
class PoseError:
    """One sensor's pose error after the best rigid fit of the estimate onto the truth."""

    name: str
    rotation_deg: float
    translation_mm: float  # distance between the estimated and the true camera centre
    height_mm: float  # error of the camera's height above the floor (world z, before fitting)


def calibration_errors(estimate: RigCalibration, truth: RigCalibration) -> list[PoseError]:
    """Per-sensor pose errors of ``estimate`` against ``truth``.

    A calibration fixes its own world frame (the floor, with an arbitrary heading), so the
    estimate is first moved rigidly onto the truth (``align_to_truth``, least squares over all
    camera centres, no scale): what remains is each camera's own error, with no camera singled
    out as the reference. The height error compares world z as estimated, which is meaningful
    when both put the floor at z = 0.
    """
    aligned = align_to_truth(estimate, truth)
    out = []
    for true in truth.sensors:
        est = aligned.sensor(true.camera_serial, true.side).pose
        raw = estimate.sensor(true.camera_serial, true.side).pose
        out.append(
            PoseError(
                name=true.name,
                rotation_deg=rotation_angle_deg(est.R @ true.pose.R.T),
                translation_mm=float(1000 * np.linalg.norm(est.centre_m - true.pose.centre_m)),
                height_mm=float(1000 * (raw.centre_m[2] - true.pose.centre_m[2])),
            )
        )
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix, in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def align_to_truth(estimate: RigCalibration, truth: RigCalibration) -> RigCalibration:
    """``estimate`` moved rigidly into ``truth``'s world frame (Kabsch on the sensor centres).

    A wand calibration chooses its own world frame (the floor, with an arbitrary heading); to
    compare renders with the sim's ground truth views, express it in the sim's frame. Only the
    gauge changes: the cameras' poses relative to each other stay as estimated.
    """
    pairs = [(s, truth.sensor(s.camera_serial, s.side)) for s in estimate.sensors]
    a = np.array([s.pose.centre_m for s, _ in pairs])
    b = np.array([t.pose.centre_m for _, t in pairs])
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T  # estimate world -> truth world
    est_to_truth = Pose(R=R, t_m=cb - R @ ca)
    sensors = tuple(
        dataclasses.replace(s, pose=s.pose.compose(est_to_truth.inverse()))
        for s in estimate.sensors
    )
    return dataclasses.replace(estimate, sensors=sensors)


SPHERE_CLEARANCE_PX = 8.0  # image gap to any other sphere for a sphere to count as whole


def wand_sphere_whole(world: World, render: Render, t_s: float, k: int) -> bool:
    """Wand sphere ``k`` is whole in ``render`` (a view of ``world`` at ``t_s``): not cut by the
    image border, nothing in front of it but the wand's own rod (it runs through the spheres and,
    where it leaves one towards the camera, crosses a little of its outline on every real wand
    too), no other sphere within ``SPHERE_CLEARANCE_PX`` of its outline: where a detector's centre
    can be held to the truth. (A detector that finds blobs on a coarser, closed mask sees two
    outlines a few pixels apart as one blob, which it must drop rather than measure.)"""
    centres = world.wand_centres(t_s)
    if centres is None:
        return False
    px, z = render.camera.project(centres[k : k + 1])
    rod = next(i for i, o in enumerate(world.scene_at(t_s).objects) if o.name == "wand_rod")
    oi = render.object_index
    H, W = oi.shape
    r = render.camera.intrinsics.fx_px * world.config.wand.radius_m / z[0]  # ~ the semi-minor axis
    u, v = px[0]
    m = int(r) + int(SPHERE_CLEARANCE_PX) + 2
    if not (m <= u < W - m and m <= v < H - m):
        return False
    y0, x0 = int(v) - m, int(u) - m
    ys, xs = np.mgrid[y0 : y0 + 2 * m + 1, x0 : x0 + 2 * m + 1]
    d = np.hypot(xs - u, ys - v)
    win = oi[y0 : y0 + 2 * m + 1, x0 : x0 + 2 * m + 1]
    ours = (win == SPHERE_OBJECT_BASE + k) | (win == rod)
    if (win == SPHERE_OBJECT_BASE + k).sum() < 0.6 * math.pi * r * r:
        return False
    if not ours[d <= r - 0.8].all():
        return False
    near = win[d <= r + SPHERE_CLEARANCE_PX]
    return not ((near >= SPHERE_OBJECT_BASE) & (near != SPHERE_OBJECT_BASE + k)).any()


def wand_axis_angle_deg(world: World, camera: Camera, t_s: float) -> float:
    """Angle between the wand's axis and ``camera``'s line of sight to its middle sphere at
    ``t_s``: 90 when the wand lies across the view, 0 when it points at the camera (its spheres
    then line up behind each other in the image)."""
    centres = world.wand_centres(t_s)
    if centres is None:
        raise ValueError(f"world seed {world.config.seed} has no wand at t={t_s} s")
    local = camera.pose.transform(centres)
    axis = (local[-1] - local[0]) / np.linalg.norm(local[-1] - local[0])
    sight = local[1] / np.linalg.norm(local[1])
    return float(np.degrees(np.arccos(min(1.0, abs(float(axis @ sight))))))


def wand_in_clear_view(
    world: World, camera: Camera, t_s: float, *, max_range_m: float, min_axis_angle_deg: float
) -> bool:
    """From the geometry alone, without rendering: all three spheres of the wand at ``t_s`` are
    in front of ``camera``, inside its image with the margin ``wand_sphere_whole`` asks for, no
    farther than ``max_range_m``, their outlines at least ``SPHERE_CLEARANCE_PX`` apart, and
    the wand at least ``min_axis_angle_deg`` from pointing at the camera. Whether something
    hides a sphere only a render can tell (``wand_sphere_whole``); this picks the times worth
    rendering."""
    centres = world.wand_centres(t_s)
    if centres is None:
        return False
    local = camera.pose.transform(centres)
    if (local[:, 2] < 0.3).any() or (np.linalg.norm(local, axis=1) > max_range_m).any():
        return False
    px, z = camera.project(centres)
    r = camera.intrinsics.fx_px * world.config.wand.radius_m / z
    m = r + SPHERE_CLEARANCE_PX + 2
    k = camera.intrinsics
    if not ((px[:, 0] >= m) & (px[:, 0] < k.width_px - m)).all():
        return False
    if not ((px[:, 1] >= m) & (px[:, 1] < k.height_px - m)).all():
        return False
    for i, j in ((0, 1), (1, 2), (0, 2)):
        if np.linalg.norm(px[i] - px[j]) - r[i] - r[j] < SPHERE_CLEARANCE_PX:
            return False
    return wand_axis_angle_deg(world, camera, t_s) >= min_axis_angle_deg


CAMOUFLAGE_CHROMA = 0.1  # chromaticity distance (r, g, b summing to 1) within which colours match


def wand_sphere_camouflaged(world: World, render: Render, t_s: float, k: int) -> bool:
    """Wand sphere ``k`` is seen in front of something of its own colour in ``render``: more
    than 5 % of the room just outside its outline (2-4 px out) matches the sphere's chromaticity
    (in the sim, the orange patches on the equipment's plastic), or a lit screen lies there
    (its yellow traces have the spheres' hue, and its 1 px lines cross the outline). There is no
    clean outline to find by colour, so a colour detector's centre cannot be held to the truth
    even where the sphere is whole (``wand_sphere_whole``)."""
    centres = world.wand_centres(t_s)
    if centres is None:
        return False
    px, z = render.camera.project(centres[k : k + 1])
    r = render.camera.intrinsics.fx_px * world.config.wand.radius_m / z[0]
    u, v = px[0]
    m = int(r) + 6
    H, W = render.object_index.shape
    if z[0] <= 0 or not (m <= u < W - m and m <= v < H - m):
        return False
    y0, x0 = int(v) - m, int(u) - m
    ys, xs = np.mgrid[y0 : y0 + 2 * m + 1, x0 : x0 + 2 * m + 1]
    d = np.hypot(xs - u, ys - v)
    rgb = render.image_rgb[y0 : y0 + 2 * m + 1, x0 : x0 + 2 * m + 1].astype(float) + 1.0
    chroma = rgb / rgb.sum(axis=2, keepdims=True)
    oi = render.object_index[y0 : y0 + 2 * m + 1, x0 : x0 + 2 * m + 1]
    inside = (oi == SPHERE_OBJECT_BASE + k) & (d < r - 1)
    objects = world.scene_at(t_s).objects
    rod = next(i for i, o in enumerate(objects) if o.name == "wand_rod")
    ring = (d > r + 1.5) & (d < r + 4) & (oi < SPHERE_OBJECT_BASE) & (oi != rod)
    if not inside.any() or not ring.any():
        return False
    if any(objects[i].emission > 0 for i in np.unique(oi[ring]) if 0 <= i < len(objects)):
        return True
    own = np.median(chroma[inside], axis=0)
    matches = np.linalg.norm(chroma[ring] - own, axis=1) < CAMOUFLAGE_CHROMA
    return bool(matches.mean() > 0.05)
