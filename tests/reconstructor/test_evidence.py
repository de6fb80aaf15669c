"""The evidence a case stores with each timestamp (``reconstructor/depth/evidence.py``): what the
stereo pairs saw, every occupied cell of it, each with the depth uncertainty of the best camera
that saw it and which cameras saw it; and it survives the model file (``storage.write_model`` /
``load_evidence`` / ``load_observation``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.camera import Intrinsics, Pose
from reconstructor.case import storage
from reconstructor.case.index import Entry, checksum_file
from reconstructor.depth.evidence import CELL_M, observed_points
from reconstructor.depth.stereo import DepthMap
from tests.reconstructor.test_ply import random_gaussians

K = Intrinsics(width_px=160, height_px=100, fx_px=120.0, fy_px=120.0, cx_px=79.5, cy_px=49.5)


def _looking_down(height_m: float, baseline_m: float, floor_depth_m: float | None = None):
    """A camera ``height_m`` above the origin looking straight down at the floor (z = 0), and
    its depth map of it: valid everywhere, depth ``height_m`` (or ``floor_depth_m``)."""
    R = np.diag([1.0, -1.0, -1.0])  # camera z points down the world's -z
    pose = Pose(R=R, t_m=-R @ np.array([0.0, 0.0, height_m]))
    depth = np.full((K.height_px, K.width_px), floor_depth_m or height_m, np.float32)
    dm = DepthMap(depth_m=depth, valid=np.ones(depth.shape, bool), disparity_px=depth * 0,
                  intrinsics=K, rect_from_left=np.eye(3), baseline_m=baseline_m,
                  rgb=np.zeros((*depth.shape, 3), np.uint8))  # fmt: skip
    return dm, pose


def test_every_cell_seen_is_kept_with_the_best_cameras_depth_uncertainty():
    """Two cameras see the same floor, one from 1 m, one from 2 m (a pixel 1.7 cm across, under
    a cell): the evidence is one point per occupied cell (as many as the floor's seen area
    holds, with no cap), on the floor, and where both saw a cell its uncertainty is the near
    camera's z^2 / (f B)."""
    near, near_pose = _looking_down(1.0, 0.12)
    far, far_pose = _looking_down(2.0, 0.12)
    seen = observed_points({"SN1": near, "SN2": far}, {"SN1": near_pose, "SN2": far_pose})
    assert np.allclose(seen.points_m[:, 2], 0.0, atol=1e-6)
    # the far camera sees a floor patch twice as wide: cells of 2 cm across it, each once
    half_m = np.array([K.cx_px + 0.5, K.cy_px + 0.5]) / K.fx_px * 2.0
    cells = np.prod(np.floor(half_m / CELL_M) * 2 + 1)
    assert abs(len(seen) - cells) / cells < 0.05
    cells_xy = np.floor(seen.points_m[:, :2] / CELL_M)
    assert len(np.unique(cells_xy, axis=0)) == len(seen)
    centre = np.all(np.abs(seen.points_m[:, :2]) < 0.3, axis=1)  # inside both views
    assert np.allclose(seen.m_per_px[centre], 1.0**2 / (120.0 * 0.12))
    assert np.allclose(seen.m_per_px[np.abs(seen.points_m[:, 0]) > 0.8], 2.0**2 / (120.0 * 0.12))
    # which cameras saw each cell: both inside the near camera's patch, the far one outside it
    assert seen.cameras == ("SN1", "SN2") and seen.seen_by.dtype == np.uint8
    assert np.all(seen.seen_by[centre] == 0b11)
    assert np.all(seen.seen_by[np.abs(seen.points_m[:, 0]) > 0.8] == 0b10)
    assert set(np.unique(seen.seen_by)) == {0b10, 0b11}


def test_the_depth_uncertainty_is_stored_with_the_points_and_read_back_in_their_order(
    tmp_path: Path,
):
    rng = np.random.default_rng(3)
    points = rng.uniform([-3.0, -2.5, 0.0], [3.0, 2.5, 2.8], size=(4000, 3))
    noise = 0.02 + np.linalg.norm(points, axis=1) ** 2 / 50.0  # each point its own value
    g = random_gaussians(50, 0, seed=1)
    path = tmp_path / "models" / "a.npz"
    storage.write_model(path, g, points_m=points, points_noise=noise)
    digest, size = checksum_file(path)
    entry = Entry(name="a", t_s=0.0, set_index=0, model="models/a.npz", xxh3_64=digest,
                  bytes=size, status="done", gaussians=g.num)  # fmt: skip
    loaded = storage.load_evidence(tmp_path, entry)
    assert loaded is not None and loaded[1] is not None
    back, back_noise = loaded
    # match each point read back to the one written (the file stores them sorted)
    order = np.lexsort(np.rint(points / storage.POINTS_STEP_M).T[::-1])
    assert np.allclose(back, points[order], atol=storage.POINTS_STEP_M)
    assert np.allclose(back_noise, noise[order], atol=storage.NOISE_STEP_M)
    # a file written without them (older cases) reads back its points and None
    old = tmp_path / "models" / "b.npz"
    storage.write_model(old, g, points_m=points)
    digest, size = checksum_file(old)
    entry = Entry(name="b", t_s=0.0, set_index=0, model="models/b.npz", xxh3_64=digest,
                  bytes=size, status="done", gaussians=g.num)  # fmt: skip
    loaded = storage.load_evidence(tmp_path, entry)
    assert loaded is not None and loaded[1] is None and len(loaded[0]) == len(points)


def test_which_cameras_saw_each_point_is_stored_with_them_and_older_files_say_unknown(
    tmp_path: Path,
):
    rng = np.random.default_rng(4)
    points = rng.uniform([-3.0, -2.5, 0.0], [3.0, 2.5, 2.8], size=(4000, 3))
    masks = rng.integers(1, 16, size=len(points)).astype(np.uint8)  # four cameras
    cameras = ("SN11", "SN12", "SN13", "SN14")
    g = random_gaussians(50, 0, seed=1)

    def entry_of(name: str) -> Entry:
        path = tmp_path / "models" / f"{name}.npz"
        digest, size = checksum_file(path)
        return Entry(name=name, t_s=0.0, set_index=0, model=f"models/{name}.npz",
                     xxh3_64=digest, bytes=size, status="done", gaussians=g.num)  # fmt: skip

    storage.write_model(tmp_path / "models" / "a.npz", g, points_m=points,
                        points_noise=np.full(len(points), 0.1), points_seen_by=masks,
                        points_cameras=cameras)  # fmt: skip
    seen = storage.load_observation(tmp_path, entry_of("a"))
    assert seen is not None and seen.seen_by is not None and seen.cameras == cameras
    order = np.lexsort(np.rint(points / storage.POINTS_STEP_M).T[::-1])
    assert np.array_equal(seen.seen_by, masks[order])
    assert storage.stores_seen_by(tmp_path, entry_of("a"))
    # the points and noise read as before, for a reader that does not know the masks
    back = storage.load_evidence(tmp_path, entry_of("a"))
    assert back is not None and np.allclose(back[0], seen.points_m)
    # a file written before the masks were stored: unknown, not "no camera"
    storage.write_model(tmp_path / "models" / "b.npz", g, points_m=points)
    old = storage.load_observation(tmp_path, entry_of("b"))
    assert old is not None and old.seen_by is None and old.cameras == ()
    assert not storage.stores_seen_by(tmp_path, entry_of("b"))
    # a mask with a bit for a camera the file does not name is refused when written
    with pytest.raises(ValueError, match="cameras"):
        storage.write_model(tmp_path / "models" / "c.npz", g, points_m=points,
                            points_seen_by=masks, points_cameras=cameras[:3])  # fmt: skip
