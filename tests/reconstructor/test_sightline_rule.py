"""The sightline's occluder rule on hand-built models: a wall made of many translucent Gaussians
(as training leaves a surface) and one made of opaque ones (as a true surface is sampled), in
front of a screen 3 m from the eye. ``SightlineConfig.conserve_opacity``: a shrunk occluder keeps
its integrated opacity, so a translucent wall stays a wall while an opaque wall's edge loses its
fringe."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from protocol.formats.site import SiteBox
from reconstructor.raster import RasterConfig
from reconstructor.replay.sightline import SightlineConfig, visible_fraction
from reconstructor.splats.gaussians import GaussianInitConfig, init_from_points

EYE = np.array([0.0, 0.0, 1.6])
SCREEN = SiteBox(name="screen", centre_m=(3.0, 0.0, 1.6), size_m=(0.02, 0.6, 0.4),
                 yaw_deg=180.0, front_only=True)  # fmt: skip
RASTER = RasterConfig(near_m=0.2)
SPACING_M = 0.02


def wall(opacity: float, y_from_m: float, y_to_m: float):
    """A vertical wall 1.5 m in front of the eye, across ``y_from_m``..``y_to_m``, its Gaussians
    on a 2 cm grid, each as wide as that spacing (``init_from_points``)."""
    y = np.arange(y_from_m, y_to_m + 1e-9, SPACING_M)
    z = np.arange(1.0, 2.2 + 1e-9, SPACING_M)
    yy, zz = np.meshgrid(y, z)
    pts = np.stack([np.full(yy.size, 1.5), yy.ravel(), zz.ravel()], 1)
    return init_from_points(pts, np.full_like(pts, 0.5), GaussianInitConfig(opacity=opacity))


def answer(g, scale: float, conserve: bool) -> float:
    cfg = SightlineConfig(occluder_scale=scale, conserve_opacity=conserve)
    return visible_fraction(g, EYE, SCREEN, RASTER, config=cfg)[0]


def test_a_wall_of_translucent_gaussians_still_hides_the_screen_when_its_gaussians_shrink():
    """A trained model's surface is opaque only where many faint Gaussians overlap (median
    opacity 0.01-0.03 on the trained case). Shrunk to half with their opacity as it was, the
    wall reads as see-through; with each Gaussian's integrated opacity kept, it still hides
    the whole screen, as it does at full size."""
    g = wall(0.2, -1.0, 1.0)
    assert answer(g, 1.0, conserve=False) == 0.0  # the wall, at full size, is a wall
    assert answer(g, 0.5, conserve=False) == 1.0  # shrunk alone: the view goes through it
    assert answer(g, 0.5, conserve=True) == 0.0


def test_an_opaque_walls_edge_loses_its_fringe_with_or_without_conserving_opacity():
    """A wall of opaque Gaussians (a true surface's 0.9) that ends at the screen's centre line
    hides half of it (grid samples: exactly half lie behind it). At full size each edge
    Gaussian's tail reaches past the wall's end and hides more; shrunk, conserving opacity
    cannot make an already opaque Gaussian much more so, and the answer comes back to the
    geometric half."""
    # the wall ends where the screen's middle projects (y = 0 at 3 m is y = 0 at 1.5 m)
    g = wall(0.9, -1.0, -SPACING_M / 2)
    full = answer(g, 1.0, conserve=False)
    fixed = answer(g, 0.5, conserve=False)
    kept = answer(g, 0.5, conserve=True)
    assert full < 0.45, f"full size: {full:.2f} (the fringe hides more than half)"
    assert kept == pytest.approx(0.5, abs=0.05) and fixed == pytest.approx(0.5, abs=0.05)


def test_conserving_opacity_changes_nothing_at_full_size():
    g = wall(0.05, -1.0, 1.0)
    cfg = SightlineConfig(occluder_scale=1.0)
    a = visible_fraction(g, EYE, SCREEN, RASTER, config=cfg)[0]
    b = visible_fraction(
        g, EYE, SCREEN, RASTER, config=dataclasses.replace(cfg, conserve_opacity=True)
    )[0]
    assert a == b
