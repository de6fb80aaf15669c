"""The wand in the sim's images is where its ground truth says, to sub-pixel accuracy."""

from __future__ import annotations

import numpy as np
import pytest

from sim.render import SPHERE_OBJECT_BASE


def _silhouette(rgb: np.ndarray) -> np.ndarray:
    """The sphere's silhouette from the image alone: orange is red well above blue, whether
    in shadow or clipped near a lamp, while the room's greys are not. Thresholding at half the
    window's maximum contrast puts the edge where a pixel is half covered."""
    contrast = rgb[..., 0].astype(float) - rgb[..., 2].astype(float)
    return (contrast > 0.5 * contrast.max()).astype(float)


def test_sphere_centres_project_to_where_the_spheres_appear(wand_world):
    world = wand_world
    radius = world.config.wand.radius_m
    checked = 0
    errors: list[float] = []
    # the operator's tour takes the wand near each camera too; the check below is for 2.5 m
    # and beyond, where the ellipse bias is small (it grows as a sphere comes near, off-axis)
    for t in (5.0, 7.5, 10.0, 12.5, 15.0):
        centres = world.wand_centres(t)
        for unit in world.rig:
            view = world.render_sensor(unit.index, "left", t, "HD1200")
            px, depth = view.camera.project(centres)
            for k in range(3):
                expected_area = np.pi * (view.camera.intrinsics.fx_px * radius / depth[k]) ** 2
                seen = (view.object_index == SPHERE_OBJECT_BASE + k).sum()
                if seen < 0.9 * expected_area or depth[k] < 2.5:  # occluded, out of view, near
                    continue
                u, v = np.round(px[k]).astype(int)
                half = int(np.ceil(view.camera.intrinsics.fx_px * radius / depth[k])) + 3
                others = np.delete(px, k, axis=0)
                if (np.abs(others - px[k]).max(axis=1) < 2 * half + 1).any():
                    continue  # another sphere in the window: the silhouette is not this one's
                win = view.image_rgb[v - half : v + half + 1, u - half : u + half + 1]
                w = _silhouette(win)
                ys, xs = np.mgrid[v - half : v + half + 1, u - half : u + half + 1]
                centroid = np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()
                # the blob's centre is the projected centre, up to the ellipse bias (< 0.3 px
                # at these distances), the shading's asymmetry and the 10 px blob's pixelation
                errors.append(np.linalg.norm(centroid - px[k]))
                checked += 1
    assert checked >= 12
    print("sphere centre errors (px):", np.round(errors, 2))
    assert np.median(errors) < 0.6
    assert max(errors) < 1.0


def test_wand_lies_on_the_floor_first_then_moves(wand_world):
    first = wand_world.wand_centres(0.5)
    np.testing.assert_allclose(first[:, 2], wand_world.config.wand.radius_m, atol=1e-9)
    later = wand_world.wand_centres(8.0)
    assert later[:, 2].min() > 0.3
    # the spheres keep the wand's geometry at every time
    for t in np.linspace(0, 30, 61):
        c = wand_world.wand_centres(float(t))
        d = np.linalg.norm(np.diff(c, axis=0), axis=1) * 1000
        np.testing.assert_allclose(d, wand_world.config.wand.distances_mm[:2], atol=1e-6)
        assert wand_world.config.room.contains(c.mean(axis=0))


def test_no_wand_outside_a_wand_session(world):
    assert world.wand_centres(1.0) is None
    view = world.render_sensor(0, "left", 1.0, "SVGA")
    assert not (view.object_index >= SPHERE_OBJECT_BASE).any()


@pytest.mark.parametrize("bad", [(0.0, 100.0, 110.0), (0.0, 150.0, 100.0), (0.0, 20.0, 400.0)])
def test_bad_wand_geometry_is_refused(bad):
    from protocol.formats.wand import WandSpec, WandSpecError

    with pytest.raises(WandSpecError):
        WandSpec(sphere_positions_mm=bad)
