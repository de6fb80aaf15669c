"""A fixed camera's fast path: the static room rendered once, then only the moving objects over
it, and the wand's spheres supersampled only where they can reach. Every evaluation's truth
comes from these images, so the fast path must give the full render's pixels."""

from __future__ import annotations

import numpy as np
import pytest

from sim import kernels
from sim.geometry import box
from sim.render import (
    SPHERE_OBJECT_BASE,
    FrameScene,
    moving_region,
    ray_directions,
    render_view,
)
from sim.room import SceneObject
from sim.spheres import composite_spheres, composite_spheres_reference

# wand phase, seed 5: the operator and the wand in view of these sensors at these times
FRAMES = ((0, "left", 6.3), (1, "right", 9.1), (3, "left", 13.7), (2, "right", 21.2))


def _names(world, objects: np.ndarray) -> set[str]:
    n_static = len(world.static_objects)
    return {
        world._moving_cache(0.0).objects[k - n_static].name.split(":")[0]
        for k in np.unique(objects)
        if n_static <= k < SPHERE_OBJECT_BASE
    }


@pytest.mark.parametrize(("unit", "side", "t"), FRAMES)
def test_a_rig_camera_renders_the_moving_operator_and_wand_as_the_full_render(
    wand_world, unit, side, t
):
    """The fast path gives the one-scene render's pixels. The one exception allowed: a ray
    through an edge that two room surfaces share hits both at the same depth, and which of the
    two a BVH reports depends on the BVH; there the fast path keeps the room render's choice."""
    world = wand_world
    cam = world.sensor(unit, side, "SVGA")
    fast = _assert_fast_path_is_the_full_render(world, cam, t)
    # not a vacuous comparison: the operator and a wand sphere are in this view
    assert {"wand_operator", "wand_rod"} <= _names(world, fast.object_index)
    assert (fast.object_index >= SPHERE_OBJECT_BASE).sum() > 10


def _assert_fast_path_is_the_full_render(world, cam, t):
    """The fast path's render of ``cam`` at ``t`` (returned) against the one-scene render."""
    full = render_view(world.scene_at(t), cam)
    fast = world._render_view(cam, t)
    room = world._background(cam)
    np.testing.assert_array_equal(fast.depth_m, full.depth_m)
    differs = (fast.radiance != full.radiance).any(axis=-1) | (
        fast.object_index != full.object_index
    )
    room_tie = (room.radiance != full.radiance).any(axis=-1) & (
        full.object_index < len(world.static_objects)
    )
    assert not (differs & ~room_tie).any(), np.argwhere(differs & ~room_tie)[:5]
    assert differs.sum() <= 4
    return fast


@pytest.mark.parametrize("phase", ["wand", "intraoperative"])
def test_the_region_cast_holds_every_pixel_a_moving_object_covers(phase, wand_world, world):
    """Pixels outside the region come from the room's render: no moving object may reach one."""
    w = wand_world if phase == "wand" else world
    checked = 0
    for t in (3.1, 8.4, 16.9):
        moving = w._moving_cache(t)
        for unit in range(len(w.rig)):
            cam = w.sensor(unit, "left", "SVGA")
            region = moving_region(cam, [o.mesh for o in moving.objects])
            assert region is not None, (t, cam.name)  # no mesh holds a rig camera
            checked += int(_assert_region_holds_every_hit(cam, moving, region) > 0)
    assert checked >= 4


# seed 5: views where the lens folds the projection of a part of the operator far outside the
# view into odd places (the region was every pixel before: a sixth of a wand view's cost)
FOLDED = ((1, 5.5), (2, 1.0))


@pytest.mark.parametrize(("unit", "t"), FOLDED)
def test_a_mesh_the_lens_folds_is_cast_only_where_its_rays_are(wand_world, unit, t):
    """Bounded in normalized image coordinates, such a mesh costs a small region, and the fast
    path still gives the full render's pixels."""
    world = wand_world
    cam = world.sensor(unit, "left", "SVGA")
    moving = world._moving_cache(t)
    region = moving_region(cam, [o.mesh for o in moving.objects])
    n_pixels = cam.intrinsics.width_px * cam.intrinsics.height_px
    assert region is not None and len(region) < n_pixels / 4
    assert _assert_region_holds_every_hit(cam, moving, region) > 0  # the operator is in view
    _assert_fast_path_is_the_full_render(world, cam, t)


def test_a_mesh_beside_the_camera_is_cast_where_its_bounding_sphere_is(wand_world):
    """A box reaching behind the camera's plane at its side: the pixels whose rays pass within
    its bounding sphere, which hold every pixel it covers; around the camera, every pixel."""
    world = wand_world
    cam = world.sensor(0, "left", "SVGA")
    side, forward = cam.pose.R[0], cam.pose.R[2]
    beside = box(cam.pose.centre_m + 0.4 * side + 0.12 * forward, (0.3, 0.3, 0.3))
    z = (beside.vertices @ cam.pose.R[2] + cam.pose.t_m[2]).astype(np.float64)
    assert z.min() < 0.0 < z.max()  # it reaches behind the camera's plane
    scene = FrameScene([SceneObject("probe", beside, "wall")], world.lights, world.textures)
    region = moving_region(cam, [beside])
    n_pixels = cam.intrinsics.width_px * cam.intrinsics.height_px
    assert region is not None and 0 < len(region) < n_pixels / 2
    hits = _assert_region_holds_every_hit(cam, scene, region)
    assert hits > 1000  # not a vacuous check: the box covers part of the view
    around = box(cam.pose.centre_m, (0.3, 0.3, 0.3))
    assert moving_region(cam, [around]) is None


def _assert_region_holds_every_hit(cam, scene, region) -> int:
    """Every pixel whose ray hits ``scene`` is in ``region``; the number of such pixels."""
    dirs = ray_directions(cam.intrinsics).reshape(-1, 3)
    rays = kernels.make_rays(
        dirs, cam.pose.R.astype(np.float32), cam.pose.centre_m.astype(np.float32)
    )
    _, obj, _ = scene.cast_rays(rays)
    inside = np.zeros(len(dirs), bool)
    inside[region] = True
    hits = obj >= 0
    assert not (hits & ~inside).any(), np.flatnonzero(hits & ~inside)[:5]
    return int(hits.sum())


def test_spheres_drawn_only_where_they_reach_equal_the_whole_box_supersampled(wand_world):
    """The wand's sub-pixel edges (what calibration measures) are the reference twin's, to the
    bit, at HD1200, as the wand crosses the views near and far, over the operator and the room."""
    world = wand_world
    drawn = 0
    for t in np.arange(2.5, 24.0, 1.7):
        moving = world._moving_cache(float(t))
        for unit in range(len(world.rig)):
            cam = world.sensor(unit, "left", "HD1200")
            base = world._background(cam)
            out = []
            for composite in (composite_spheres, composite_spheres_reference):
                img = [base.radiance.copy(), base.depth_m.copy(), base.object_index.copy()]
                composite(moving.spheres, moving.lights, cam, *img)
                out.append(img)
            for fast, ref in zip(*out, strict=True):
                np.testing.assert_array_equal(fast, ref)
            drawn += int((out[0][2] >= SPHERE_OBJECT_BASE).any())
    assert drawn >= 20
