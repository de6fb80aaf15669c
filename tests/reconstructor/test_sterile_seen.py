"""Seen empty (``reconstructor/replay/sterile_seen.py``): a camera that saw a surface behind a
voxel saw through it. What a reviewer relies on: air a hand entered is seen empty when the hand
is gone, a surface is never seen through, a smear in the air is seen through by another camera
at that very time; and ``sterile`` keeps a reach into such air while it drops a part whose
voxels no camera ever saw through. The scene is built geometry: a solid table block, the floor,
four cameras at the room's corners, each seeing what no box hides from it."""

from __future__ import annotations

import numpy as np

from reconstructor.replay.sterile import (
    Instant,
    Region,
    SterileConfig,
    background,
    group_events,
    moving_blobs,
)
from reconstructor.replay.sterile_seen import (
    Freespace,
    Sight,
    freespace,
    through,
    through_reference,
)
from tests.reconstructor.test_sterile import BOX, _arm, _body, _slab

CAMERAS = np.array([(2.0, 2.8, 2.4), (-2.0, 2.8, 2.4), (2.0, -2.8, 2.4), (-2.0, -2.8, 2.4)])
TABLE = (np.array([-0.6, -0.4, 0.0]), np.array([0.6, 0.4, 0.9]))  # a solid block
HAND = (np.array([-0.05, -0.05, 1.0]), np.array([0.05, 0.05, 1.1]))  # 10-20 cm above it


def _grid(lo, hi, step=0.02) -> np.ndarray:
    axes = [np.arange(a, b + 1e-9, step) if b > a else np.array([a])
            for a, b in zip(lo, hi, strict=True)]  # fmt: skip
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _surface(box) -> np.ndarray:
    (x0, y0, z0), (x1, y1, z1) = box
    return np.concatenate([
        _grid((x0, y0, z1), (x1, y1, z1)), _grid((x0, y0, z0), (x0, y1, z1)),
        _grid((x1, y0, z0), (x1, y1, z1)), _grid((x0, y0, z0), (x1, y0, z1)),
        _grid((x0, y1, z0), (x1, y1, z1)),
    ])  # fmt: skip


def _hidden(points: np.ndarray, centre: np.ndarray, box) -> np.ndarray:
    """(N,) whether the segment from ``centre`` to each point passes through ``box`` (shrunk
    by 2 mm, so a point on the box's own face is not hidden by it): the slab method."""
    lo, hi = box[0] + 0.002, box[1] - 0.002
    d = points - centre
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - centre) / d, (hi - centre) / d
    enter = np.nanmax(np.minimum(a, b), axis=1)
    leave = np.nanmin(np.maximum(a, b), axis=1)
    return (enter <= leave) & (leave > 0) & (enter < 0.998)


def _sight(hand: bool = False, smear: np.ndarray | None = None) -> Sight:
    """What the four cameras see: the floor and the table, and the hand when ``hand``;
    ``smear``: points only camera 0 reports (a wrong match in the air)."""
    floor = _grid((-2.0, -2.0, 0.0), (2.0, 2.0, 0.0), 0.04)
    boxes = [TABLE, HAND] if hand else [TABLE]
    pts = np.concatenate([floor, *(_surface(b) for b in boxes)])
    masks = np.zeros(len(pts), np.uint32)
    for c, centre in enumerate(CAMERAS):
        seen = ~np.any([_hidden(pts, centre, b) for b in boxes], axis=0)
        masks[seen] |= 1 << c
    keep = masks > 0
    pts, masks = pts[keep], masks[keep]
    if smear is not None:
        pts, masks = np.concatenate([pts, smear]), np.r_[masks, np.ones(len(smear), np.uint32)]
    return Sight(pts, np.full(len(pts), 0.02), masks, CAMERAS)


def _through(sight: Sight, voxels_m) -> np.ndarray:
    return through(sight, np.asarray(voxels_m, float), 0.05 * np.sqrt(3) / 2, 0.21, 2.0)


def test_air_a_hand_entered_is_seen_through_when_it_has_gone_and_a_surface_never_is():
    air = [0.0, 0.0, 1.05]  # the hand's middle
    side = [0.0, -0.42, 0.5]  # 2 cm out from the table's side: within a voxel of the surface
    empty, held = _through(_sight(), [air, side]), _through(_sight(hand=True), [air, side])
    assert bin(int(empty[0])).count("1") == 4  # every camera sees the table's top behind it
    assert held[0] == 0  # the hand is there: every camera sees the hand itself
    assert empty[1] == 0 and held[1] == 0  # the side: no camera sees behind it


def test_a_smear_in_the_air_is_seen_through_by_the_other_cameras_at_that_time():
    smear = _grid((-0.04, -0.04, 0.96), (0.04, 0.04, 1.0))  # 6-10 cm above the table: air
    now = _through(_sight(smear=smear), [[0.0, 0.0, 0.98]])[0]
    assert now & 0b1110 == 0b1110  # the other three saw the table behind it
    assert now & 1 == 0  # the camera that reported it cannot see past its own points


def test_through_matches_its_slow_reference():
    rng = np.random.default_rng(5)
    pts = rng.uniform((-1, -1, 0), (1, 1, 1.5), (300, 3))
    sight = Sight(pts, rng.uniform(0.01, 0.3, 300), rng.integers(1, 16, 300).astype(np.uint32),
                  CAMERAS)  # fmt: skip
    voxels = rng.uniform((-1, -1, 0), (1, 1, 1.5), (60, 3))
    for half, sigmas in ((0.0, 0.0), (0.04, 2.0)):
        fast = through(sight, voxels, half, 0.21, sigmas, bin_rad=0.15)
        slow = through_reference(sight, voxels, half, 0.21, sigmas, bin_rad=0.15)
        assert np.array_equal(fast, slow)
        assert fast.any() and not fast.all()  # the comparison is not vacuous


def test_freespace_counts_the_timestamps_a_voxel_was_seen_through():
    cfg = SterileConfig(voxel_m=0.05)
    reg = Region(BOX, cfg)
    sights = [_sight(hand=k == 2) for k in range(5)]
    free = freespace(reg, sights, [0.0, 1.0, 2.0, 3.0, 4.0])
    hand = reg.voxels(np.array([[0.0, 0.0, 1.05]]))
    assert free.now(hand, 2.0).tolist() == [False] and free.now(hand, 0.0).tolist() == [True]
    assert free.seen_empty(hand, 2.0, 0.5).tolist() == [1.0]  # at every other timestamp
    assert free.seen_empty(hand, 2.0, 10.0) is None  # no timestamp that far: cannot say


def _judged(free: Freespace | None, config: SterileConfig) -> list:
    """A person reaches into the box at 1.5 s of six timestamps 0.5 s apart."""
    rng = np.random.default_rng(0)
    eye = np.array([0.0, -0.95, 1.6])
    reg = Region(BOX, config)
    frames = [reg.select(np.concatenate([_slab(), _body(eye, rng)])) for _ in range(6)]
    frames[3] = np.concatenate([frames[3], reg.select(_arm(eye, (0.0, -0.3, 0.9), rng))])
    times = [0.5 * k for k in range(6)]
    bg = background(reg, frames, times)
    rows = [Instant(t, f"t{k}", *moving_blobs(reg, bg, f, {"p": eye}, t, None, free))
            for k, (t, f) in enumerate(zip(times, frames, strict=True))]  # fmt: skip
    return [e.start_s for e in group_events(BOX, rows, config)]


def test_a_reach_into_air_seen_empty_is_a_contact_and_into_a_surface_never_seen_through_not():
    cfg = SterileConfig(min_air_share=0.2, min_cameras=1)
    reg = Region(BOX, cfg)
    times = np.array([0.5 * k for k in range(6)])
    everything = np.arange(np.prod(reg.shape))
    seen = Freespace(np.full(reg.shape, 6, np.int32), times, [everything] * 6)
    never = Freespace(np.zeros(reg.shape, np.int32), times, [everything[:0]] * 6)
    assert _judged(None, cfg) == [1.5]  # without the cameras' masks: not applied
    assert _judged(seen, cfg) == [1.5]
    assert _judged(never, cfg) == []
    off = SterileConfig(min_air_share=0.0, min_cameras=1)
    assert _judged(never, off) == [1.5]  # turned off, the same reach is a contact again


def test_a_smear_is_seen_by_one_camera_and_a_hand_by_more():
    """A wrong match lies along one camera's rays; a hand in view is seen by each camera that
    looks at it, so a part no second camera saw is a smear (``min_cameras``)."""
    cfg = SterileConfig(voxel_m=0.05)
    reg = Region(BOX, cfg)
    smear = _grid((0.26, 0.26, 0.96), (0.3, 0.3, 1.0))  # only camera 0 reports it
    free = freespace(reg, [_sight(hand=True, smear=smear)], [0.0])
    assert free.cameras_of(reg.voxels(np.array([[0.28, 0.28, 0.98]])), 0.0) == 1
    assert free.cameras_of(reg.voxels(np.array([[0.0, 0.0, 1.1]])), 0.0) == 4  # the hand's top
    nothing = reg.voxels(np.array([[0.0, 0.0, 1.5]]))
    assert free.cameras_of(nothing, 0.0) == 0


def test_a_part_no_second_camera_saw_is_no_contact():
    cfg = SterileConfig(min_cameras=2, min_air_share=0.0)
    reg = Region(BOX, cfg)
    times = np.array([0.5 * k for k in range(6)])
    everything = np.arange(np.prod(reg.shape))
    masks = np.ones(len(everything), np.uint32)
    one = Freespace(np.zeros(reg.shape, np.int32), times, [everything[:0]] * 6,
                    [(everything, masks)] * 6)  # fmt: skip
    two = Freespace(one.counts, times, one.through, [(everything, masks | 2)] * 6)
    assert _judged(one, cfg) == []
    assert _judged(two, cfg) == [1.5]
    assert _judged(one, SterileConfig(min_air_share=0.0, min_cameras=1)) == [1.5]
