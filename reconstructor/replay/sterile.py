"""Sterile-field contact: when reconstructed things that are not part of the static scene enter a
field box (the drape, the back table), grouped into events, each with the nearest role.

**Static scene.** Each timestamp of a case is reconstructed on its own, so the same drape is
made of different points each time; what stays is where they are (the points are what each
timestamp's stereo pairs saw, one per occupied 2 cm cell, stored with its model:
``depth/evidence.py``; for a case stored without them, the centres of its Gaussians with
opacity at least ``min_opacity``). The region around the
field (the box grown by ``reach_m``) is cut into ``voxel_m`` voxels; a voxel holding a point
at ``static_fraction`` or more of the case's timestamps is the static scene (a per-voxel
median over time, the classic background model of fixed cameras), grown by one voxel so that a
surface's jitter between reconstructions is not motion.
This needs no empty-room recording; its price: something that stays in the field for more than
``static_fraction`` of the case becomes background (use a shorter ``--from``/``--to`` span).

**Contacts.** At each timestamp the other occupied voxels are the moving things. They are
split into 26-connected blobs over the whole region, so that a hand in the field stays joined
to its arm and body outside it. A blob that reaches into the box is judged on five pieces of
evidence, each against a kind of false event measured on the sim's cases (docs/replay.md):

1. *Flicker.* A voxel's fill share at the case's other timestamps (more than
   ``flicker_window_s`` away, so a touch's own timestamps do not count against it) says how
   often something is there anyway: a table's ragged underside beside a passer-by, the smear
   between a walking body and the drape. A hand's voxels are empty but for its touches. A blob
   whose in-field points sit in voxels with a median share of ``max_flicker`` or more is
   noise (the price: a contact repeated at one spot for a fifth of the span looks like flicker,
   as one held for half of it looks static; review a shorter ``--from``/``--to``).
2. *Who.* Each point goes to the role whose body it is joined to (``split_by_role``): a
   role's body is the blob's voxels within ``body_radius_m`` of its eye's vertical (people
   stand), and every voxel goes to the body it is reached from first through the blob's own
   voxels, so a hand far out over the field follows its arm back to its owner even where it
   is nearer another person's eye (without a body in the blob: the nearest eye). Each role's
   part is judged alone: a passer-by merged with the arm that reaches in neither takes the
   contact nor hides it. A part needs at least
   ``min_points`` points inside the box and ``min_outside`` outside it (the arm that
   reaches in; a lone blob wholly inside is a floater: a thing dropped into the field alone is
   not a contact), and a median distance to its role's eye of at most
   ``max_role_distance_m`` (farther, it is nobody's arm).
3. *An arm.* A hand in the field hangs from a shoulder, about 0.2 m below the eyes; the arm's
   top may merge into a still body's static voxels (with every cell stereo saw kept, a still
   body's voxels are static up to the elbow, about 0.5 m below the eyes), so a part must rise
   to within ``max_shoulder_drop_m`` below its role's eye. A low heap of noise beside the drape
   does not.

4. *Seen empty* (``sterile_seen.py``, with the cameras that saw each stored cell): a voxel a
   camera saw through (a cell farther along its ray) at ``air_seen_empty`` of the other
   timestamps is air; a part needs ``min_air_share`` of its in-box points in air. The room's
   surfaces that stereo finds only sometimes (the drape's hanging side, the table's padding) are
   too rare to be static or flicker, but no camera ever sees through them.
5. *Two cameras.* A wrong stereo match lies along one camera's rays; a part's in-box points
   must have been seen by ``min_cameras`` cameras (the smear in the air beside a resting hand
   was seen by one).

6. *Moved there* (an event, not a timestamp): a hand that reaches in crosses the box's face
   where nothing was a moment before, while a smear just inside the face beside someone
   standing at it hangs off a body that was there all along. Where a part crosses into the box
   is its points outside the box within ``crossing_radius_m`` of its in-box points; their voxels'
   mean fill share over the timestamps ``moved_window_s`` before now is the part's
   ``filled_before``. An event none of whose timestamps has ``filled_before`` of at most
   ``max_filled_before`` is dropped (a timestamp with no earlier ones in the window says
   nothing, and keeps its event).

*Not followed.* Inside a gap of a role's track (nobody followed that person then: hidden
from every camera, or between two tracks joined as one role) or outside its keyframes, the
role has no eye: it seeds no body and takes no contact (its held eye is where it was, not where
it is). A part that no followed role's arm holds is then reported as ``NOT_FOLLOWED``, judged on
the tests that need no eye (the counts, flicker, seen empty, two cameras), rather than dropped:
the touch is kept, and given to nobody we did not follow.

Parts of ``sterile_roles`` (the gowned team, whose work in the field is not a contact) are
kept apart. Without roles, only the tests that need no eye apply.

**Margin** (off by default: measured, it removed no false event; docs/replay.md). With
``margin_sigmas`` above 0, a point counts as inside the box only where it lies deeper inside
than ``margin_sigmas`` times its depth uncertainty: the matcher's disparity noise
(``disparity_noise_px``) times the metres of depth per pixel of disparity of the best camera
that saw it (stored with each point). Stereo puts a hand that hovers beside the drape some
centimetres into the box (0.2 px is 6 cm at 3.5 m); such a point is no evidence of a touch.
The top face is exempt unless ``margin_on_top``: a hand on the drape lies just under it by
construction of the box.

**Events.** A role's consecutive contact timestamps form one event (``max_gap`` missed
timestamps inside it are bridged); its start is its first contact timestamp, so it is late by
at most the case's sampling interval.

**One touch, one person** (``one_event_per_touch``). The split above is made at each timestamp
alone, and at some timestamps it gives part or all of a touch to a neighbour: a body that stands
beside the toucher merges with the arm and wins the hand's far voxels, or the toucher's still
body is static and the blob holds no body, so the hand goes to the nearest eye, a neighbour's.
Two roles' events are the same touch when, at timestamps at most ``max_gap`` + 1 apart, their
in-box voxels touch (26-neighbours or the same voxel); such events (of the same kind: a gowned
role's work never absorbs a contact, nor the reverse) become one event, named for the role that
holds the touch at the most timestamps (then the most points); at a timestamp only the other
held, that part is counted as the named role's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from protocol.formats.site import SiteBox
from reconstructor.errors import SterileError
from reconstructor.replay.sterile_seen import Freespace


@dataclass(frozen=True, kw_only=True)
class SterileConfig:
    voxel_m: float = 0.05  # a hand is about two voxels across
    reach_m: float = 0.8  # blobs are traced this far around the box: an arm and a shoulder
    static_fraction: float = 0.5  # occupied at least this often: the static scene
    min_opacity: float = 0.05  # fainter: pruned floaters (a fresh Gaussian starts at 0.1)
    # points of one blob inside the box for a contact: a case's stored points are one per
    # occupied 2 cm cell of what stereo saw (depth/evidence.py), so 8 is ~32 cm^2 of hand
    min_points: int = 8
    # and outside it: the forearm that reaches in, 64 cm^2 of it (a lone blob is a floater, a
    # smear in the air with a few points over the box's face no arm: docs/replay.md measured
    # 21 or more on every gowned hand at the drape, 309 or more on the scripted touches)
    min_outside: int = 16
    max_gap: int = 1  # missed timestamps bridged inside one event
    # a part's median distance from its role's eye, farther: no one's arm (a still body's full
    # reach, 0.66 m to the drape, gave 0.45-0.49 m: its moving part is the forearm and hand)
    max_role_distance_m: float = 0.5
    min_timestamps: int = 1  # 2 drops one-timestamp noise, and touches shorter than 2 intervals
    max_flicker: float = 0.2  # in-field voxels filled this often (median) are noise; 1 turns off
    flicker_window_s: float = 3.0  # ... at timestamps this far from now (a touch's own)
    max_shoulder_drop_m: float | None = 0.55  # the blob rises to this below its role's eye
    split_by_role: bool = True  # each point to the body it joins: two people touching apart
    body_radius_m: float = 0.25  # a body column about its eye: the shoulders are ~0.2 m out
    sterile_roles: tuple[str, ...] = ()
    # a point counts in the box only deeper inside than its depth uncertainty: the matcher's
    # disparity noise times the metres per pixel of the camera that saw it (depth/evidence.py)
    disparity_noise_px: float = 0.21  # the sim's floor, SGBM + WLS at SVGA (docs/replay.md)
    # 0: off (the default: on the sim's seeds it removed no false event and cost the short
    # touch most of its points and a timestamp of its start; docs/replay.md)
    margin_sigmas: float = 0.0
    margin_on_top: bool = False  # the top face too (a hand on the drape lies just under it)
    # seen empty (sterile_seen.py; needs each point's cameras): a voxel some camera saw through
    # at this share or more of the other timestamps is air (no camera sees through a surface)
    air_seen_empty: float = 0.3
    # ... and a part needs this share of its in-box points in air: one against a surface that
    # stereo finds only sometimes is that surface, not a hand (0: off; measured on three seeds
    # it removed every room-surface false event, docs/replay.md)
    min_air_share: float = 0.2
    # ... and one whose in-box points lie, at this share or more, in voxels a camera sees
    # through at the same timestamp is a smear in front of what that camera saw (1: off)
    max_seen_through_now: float = 1.0
    seen_margin_sigmas: float = 2.0  # seen through: farther than the voxel by this much noise
    seen_window_s: float = 1.0  # seen empty at timestamps this far from now (a touch's own)
    # a part's in-box points seen by fewer cameras: a wrong match along one camera's rays (1:
    # off; measured, it removed the smears in the air beside a resting hand, docs/replay.md)
    min_cameras: int = 2
    # two roles' events of one touch (their in-box voxels touching at timestamps at most
    # max_gap + 1 apart) are one event, named for who holds it most (False: one per role)
    one_event_per_touch: bool = True
    # an event's part must have crossed into the box, at one of its timestamps at least, where
    # the case was empty just before (sterile.py, test 6): its points outside the box within
    # this of its in-box points ...
    crossing_radius_m: float = 0.15
    # ... filled at the timestamps this long before now (a hand reaches in within 0.5 s) ...
    moved_window_s: tuple[float, float] = (0.5, 2.0)
    # ... at this mean share or less (1: off; measured on three seeds, the scripted touches'
    # events 0-0.09 at their emptiest timestamp, the smears beside a person standing at the
    # face 0.18-0.40 at every one: docs/replay.md)
    max_filled_before: float = 0.125

    def margin_m(self, m_per_px: np.ndarray) -> np.ndarray:
        """(N,) how deep inside a box each point must lie to count, from its metres of depth
        per pixel of disparity."""
        return self.margin_sigmas * self.disparity_noise_px * np.asarray(m_per_px, float)

    def __post_init__(self) -> None:
        if not (0.01 <= self.voxel_m <= 0.5 and 0 <= self.reach_m <= 3):
            raise ValueError(f"voxel_m {self.voxel_m} (0.01-0.5) or reach_m {self.reach_m} (0-3)")
        if not 0 < self.static_fraction <= 1:
            raise ValueError(f"static_fraction {self.static_fraction}: give (0, 1]")
        if not (0 <= self.min_opacity < 1 and self.min_points >= 1 and self.max_gap >= 0):
            raise ValueError("min_opacity in [0, 1), min_points >= 1, max_gap >= 0, please")
        if self.min_timestamps < 1 or not self.max_role_distance_m > 0:
            raise ValueError("min_timestamps >= 1 and max_role_distance_m > 0, please")
        if not self.flicker_window_s >= 0:
            raise ValueError(f"flicker_window_s {self.flicker_window_s}: give >= 0")
        if not 0 < self.max_flicker <= 1:
            raise ValueError(f"max_flicker {self.max_flicker}: give (0, 1] (1 turns it off)")
        if not 0 < self.body_radius_m <= 1:
            raise ValueError(f"body_radius_m {self.body_radius_m}: give (0, 1]")
        if self.max_shoulder_drop_m is not None and not self.max_shoulder_drop_m > 0:
            raise ValueError(f"max_shoulder_drop_m {self.max_shoulder_drop_m}: give > 0 or None")
        shares = (self.air_seen_empty, self.min_air_share)
        if not (all(0 <= v <= 1 for v in shares) and 0 < self.max_seen_through_now <= 1):
            raise ValueError("air_seen_empty and min_air_share in [0, 1], max_seen_through_now "
                             "in (0, 1], please")  # fmt: skip
        if not 1 <= self.min_cameras <= 31:
            raise ValueError(f"min_cameras {self.min_cameras}: give 1 (off) to 31")
        lo, hi = self.moved_window_s
        if not (
            0 < self.crossing_radius_m <= 1 and 0 <= lo < hi and 0 <= self.max_filled_before <= 1
        ):
            raise ValueError("crossing_radius_m in (0, 1], moved_window_s (lo, hi) with 0 <= lo "
                             "< hi, max_filled_before in [0, 1], please")  # fmt: skip
        if not self.seen_window_s >= 0:
            raise ValueError(f"seen_window_s {self.seen_window_s}: give >= 0")
        if not (
            self.disparity_noise_px >= 0 and min(self.margin_sigmas, self.seen_margin_sigmas) >= 0
        ):
            raise ValueError("disparity_noise_px and the margins' sigmas: give >= 0")


# The role of a contact made where some role's track was not followed (inside a gap of its
# trajectory, or outside its keyframes) and no followed role's arm holds it: a touch is never
# dropped for want of an eye, nor given to a stale one. Spaces: no role name has them.
NOT_FOLLOWED = "a person not followed"


@dataclass(frozen=True)
class Blob:
    """A moving thing that touches the field at one timestamp."""

    points_m: np.ndarray  # (N, 3) its points, all of the blob
    in_field: np.ndarray  # (N,) bool: inside the box
    role: str  # "" without roles
    role_distance_m: float  # median horizontal distance of its points to the role's eye
    # mean fill share, just before, of the voxels where it crosses into the box (test 6; NaN:
    # not known, no earlier timestamp in the window or no point outside near the box)
    filled_before: float = float("nan")

    @property
    def count(self) -> int:
        return int(self.in_field.sum())

    @property
    def contact_m(self) -> np.ndarray:
        return self.points_m[self.in_field].mean(axis=0)


@dataclass
class Instant:
    t_s: float
    model: str
    moving_in_field: int  # moving points inside the box, all blobs
    blobs: list[Blob] = field(default_factory=list)


@dataclass(frozen=True)
class Event:
    field: str
    role: str
    sterile_role: bool
    instants: tuple[Instant, ...]
    blobs: tuple[Blob, ...]  # the role's blob at each instant (largest)

    @property
    def start_s(self) -> float:
        return self.instants[0].t_s

    @property
    def end_s(self) -> float:
        return self.instants[-1].t_s

    @property
    def peak(self) -> int:
        return int(np.argmax([b.count for b in self.blobs]))


class Region:
    """The field box grown by ``reach_m``, as a voxel grid in the box's own frame."""

    def __init__(self, box: SiteBox, config: SterileConfig) -> None:
        self.box, self.config = box, config
        self.half_m = np.asarray(box.size_m) / 2 + config.reach_m
        self.shape = tuple(math.ceil(2 * h / config.voxel_m) for h in self.half_m)
        if math.prod(self.shape) > 64_000_000:
            raise SterileError(
                f"field {box.name!r}: the box and its {config.reach_m} m reach make "
                f"{math.prod(self.shape)} voxels of {config.voxel_m} m; use a smaller box"
            )

    def local(self, points_m: np.ndarray) -> np.ndarray:
        return (points_m - np.asarray(self.box.centre_m)) @ self.box.rotation

    def select(self, points_m: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> the points inside the region."""
        return points_m[self.holds(points_m)]

    def holds(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the world points lie inside the region."""
        return np.all(np.abs(self.local(points_m)) < self.half_m, axis=1)

    def depth_inside(self, points_m: np.ndarray, top: bool = True) -> np.ndarray:
        """(N,) each point's distance inside the box to its nearest face (negative outside);
        without ``top``, to its nearest face but the top one."""
        local = (points_m - np.asarray(self.box.centre_m)) @ self.box.rotation
        gap = np.asarray(self.box.size_m) / 2 - np.abs(local)
        if not top:  # the top face's gap: only a point below the box's middle is near its bottom
            gap[:, 2] = np.where(local[:, 2] < 0, gap[:, 2], np.inf)
        return np.min(gap, axis=1)

    def voxels(self, points_m: np.ndarray) -> np.ndarray:
        """(N, 3) int voxel indices of points inside the region."""
        idx = np.floor((self.local(points_m) + self.half_m) / self.config.voxel_m).astype(int)
        return np.clip(idx, 0, np.asarray(self.shape) - 1)

    def occupancy(self, points_m: np.ndarray) -> np.ndarray:
        grid = np.zeros(self.shape, bool)
        v = self.voxels(points_m)
        grid[v[:, 0], v[:, 1], v[:, 2]] = True
        return grid


@dataclass(frozen=True)
class Background:
    """What the case's reconstructions hold around a field, voxel by voxel."""

    counts: np.ndarray  # (X, Y, Z) int32: timestamps that fill each voxel
    static: np.ndarray  # (X, Y, Z) bool: the static scene, grown by one voxel
    times_s: np.ndarray  # (T,) the timestamps
    filled: list[np.ndarray]  # per timestamp, the flat indices of the voxels it fills

    def filled_before(self, voxels: np.ndarray, t_s: float, window_s: tuple[float, float]) -> float:
        """Mean share of the timestamps ``window_s`` (lo, hi) seconds before ``t_s`` at which each
        of ``voxels`` ((N, 3) indices) was filled; NaN when none is that far back or no voxel."""
        lo, hi = window_s
        ago = t_s - self.times_s
        before = np.nonzero((ago >= lo - 1e-6) & (ago <= hi + 1e-6))[0]
        if not len(before) or not len(voxels):
            return float("nan")
        flat = np.unique(np.ravel_multi_index(voxels.T, self.counts.shape))
        return float(np.mean([np.isin(flat, self.filled[k]).mean() for k in before]))

    def flicker(self, voxels: np.ndarray, t_s: float, window_s: float) -> np.ndarray:
        """(N,) share of the timestamps more than ``window_s`` from ``t_s`` that fill each of
        ``voxels`` ((N, 3) indices): how often something is there apart from now (0 when no
        timestamp is that far)."""
        flat = np.ravel_multi_index(voxels.T, self.counts.shape)
        near = np.abs(self.times_s - t_s) <= window_s
        hits = self.counts.ravel()[flat].astype(np.int64)
        for k in np.nonzero(near)[0]:
            hits -= np.isin(flat, self.filled[k])
        others = int((~near).sum())
        return hits / others if others else np.zeros(len(flat))


def background(region: Region, frames: list[np.ndarray], times_s: list[float]) -> Background:
    """Each voxel's fill count over ``frames`` (each a timestamp's points in the region) and
    the static scene: voxels filled at ``static_fraction`` or more, grown by one voxel."""
    counts = np.zeros(region.shape, np.int32)
    filled = []
    for pts in frames:
        grid = region.occupancy(pts)
        counts += grid
        filled.append(np.flatnonzero(grid))
    static = counts >= region.config.static_fraction * len(frames)
    static = ndimage.binary_dilation(static, structure=np.ones((3, 3, 3), bool))
    return Background(counts, static, np.asarray(times_s, float), filled)


def static_scene(region: Region, frames: list[np.ndarray]) -> np.ndarray:
    """(X, Y, Z) bool: the static scene of ``background``."""
    return background(region, frames, list(range(len(frames)))).static


def moving_blobs(
    region: Region, bg: Background | np.ndarray, points_m: np.ndarray,
    eyes_m: dict[str, np.ndarray | None], t_s: float = 0.0, margin_m: np.ndarray | None = None,
    free: Freespace | None = None,
) -> tuple[int, list[Blob]]:  # fmt: skip
    """(moving points inside the box, the moving blobs that touch the box) at ``t_s``.
    ``bg``: the case's background (or a bare static grid: no flicker test); ``eyes_m``: each
    role's eye then (empty: no roles; None: the role is not followed then, see
    ``NOT_FOLLOWED``); ``margin_m``: (N,) how deep inside the box each point must lie to count
    as inside (its depth uncertainty, ``SterileConfig.margin_m``; None: on the faces counts);
    ``free``: which voxels the cameras saw through (``sterile_seen.py``; None: not known)."""
    cfg = region.config
    unfollowed = any(e is None for e in eyes_m.values())
    followed = {r: e for r, e in eyes_m.items() if e is not None}
    static = bg.static if isinstance(bg, Background) else bg
    v = region.voxels(points_m)
    moving = ~static[v[:, 0], v[:, 1], v[:, 2]]
    pts, v = points_m[moving], v[moving]
    inside = region.box.contains(pts)
    if margin_m is not None:  # nearer a face than stereo can tell: not evidence of a touch
        inside &= region.depth_inside(pts, cfg.margin_on_top) > np.asarray(margin_m)[moving]
    grid = np.zeros(region.shape, bool)
    grid[v[:, 0], v[:, 1], v[:, 2]] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    point_label = labels[v[:, 0], v[:, 1], v[:, 2]]
    full_bg = bg if isinstance(bg, Background) else None
    full = full_bg if cfg.max_flicker < 1 else None
    blobs = []
    for k in np.unique(point_label[inside]) if n else []:
        whole = point_label == k
        if full is not None:
            flicker = full.flicker(v[whole & inside], t_s, cfg.flicker_window_s)
            if np.median(flicker) >= cfg.max_flicker:
                continue  # in-field voxels the case often fills: a ragged edge, not a hand
        for role, sel in _parts(
            pts, v, whole, inside, followed, cfg.split_by_role, cfg.voxel_m, cfg.body_radius_m
        ):
            n_in = int((sel & inside).sum())
            if n_in < cfg.min_points or int(sel.sum()) - n_in < cfg.min_outside:
                continue
            if free is not None and not _air_entered(free, v[sel & inside], t_s, cfg):
                continue
            dist = _distance(pts[sel], followed.get(role))
            if followed and not _an_arm_of(pts[sel], followed[role], dist, cfg):
                if not unfollowed:
                    continue  # no one's arm: noise beside the field
                role = NOT_FOLLOWED  # maybe the arm of someone whose eye we do not know now
            if unfollowed and not followed:
                role = NOT_FOLLOWED
            before = _filled_before(full_bg, pts, v, sel, inside, t_s, cfg)
            blobs.append(Blob(pts[sel], inside[sel], role, dist, before))
    return int(inside.sum()), blobs


def _filled_before(
    bg: Background | None, pts: np.ndarray, vox: np.ndarray, sel: np.ndarray,
    inside: np.ndarray, t_s: float, cfg: SterileConfig,
) -> float:  # fmt: skip
    """A part's ``Blob.filled_before``: where it crosses into the box (its points outside within
    ``crossing_radius_m`` of its in-box points), how often the case filled it just before."""
    if bg is None:
        return float("nan")
    out = sel & ~inside
    if not out.any():
        return float("nan")
    near, _ = cKDTree(pts[sel & inside]).query(pts[out], distance_upper_bound=cfg.crossing_radius_m)
    return bg.filled_before(vox[out][np.isfinite(near)], t_s, cfg.moved_window_s)


def _air_entered(free: Freespace, voxels: np.ndarray, t_s: float, cfg: SterileConfig) -> bool:
    """Whether a part's in-box voxels (one row per point) are air that something entered:
    seen through at other times (a surface never is), and not now (a smear is)."""
    if cfg.min_air_share > 0:
        share = free.seen_empty(voxels, t_s, cfg.seen_window_s)
        if share is not None and (share >= cfg.air_seen_empty).mean() < cfg.min_air_share:
            return False  # never seen through: a surface that stereo finds only sometimes
    if cfg.min_cameras > 1:
        seen_by = free.cameras_of(voxels, t_s)
        if seen_by is not None and seen_by < cfg.min_cameras:
            return False  # no second camera saw it: a smear along one camera's rays
    return not (cfg.max_seen_through_now < 1
                and free.now(voxels, t_s).mean() >= cfg.max_seen_through_now)  # fmt: skip


def _an_arm_of(points_m: np.ndarray, eye_m: np.ndarray, dist_m: float, cfg) -> bool:
    """Whether a part can be the arm of the role whose eye is ``eye_m``: near enough its eye's
    vertical (a body is within ~0.3 m of it, a reach adds an arm) and rising toward its
    shoulder (a heap of noise beside the field does not)."""
    if dist_m > cfg.max_role_distance_m:
        return False
    drop = cfg.max_shoulder_drop_m
    return drop is None or points_m[:, 2].max() >= eye_m[2] - drop


def _parts(
    pts: np.ndarray, vox: np.ndarray, sel: np.ndarray, inside: np.ndarray,
    eyes_m: dict[str, np.ndarray], split: bool, voxel_m: float, body_m: float,
) -> list[tuple[str, np.ndarray]]:  # fmt: skip
    """A blob as (role, mask) parts: whole, given to the majority of its points' nearest
    roles; or split by whose body each point hangs from (``_owners``), keeping the parts
    that hold in-field points."""
    if not eyes_m:
        return [("", sel)]
    names = list(eyes_m)
    eyes = np.stack([eyes_m[n][:2] for n in names])
    idx = np.nonzero(sel)[0]
    if not split:
        near = np.argmin(np.linalg.norm(pts[idx, None, :2] - eyes[None], axis=2), axis=1)
        return [(names[int(np.argmax(np.bincount(near, minlength=len(names))))], sel)]
    owner = _owners(pts[idx], vox[idx], eyes, voxel_m, body_m)
    parts = []
    for r in np.unique(owner[inside[idx]]):
        mask = np.zeros_like(sel)
        mask[idx[owner == r]] = True
        parts.append((names[int(r)], mask))
    return parts


_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) != (0, 0, 0)])  # fmt: skip


def _owners(
    pts: np.ndarray, vox: np.ndarray, eyes_xy: np.ndarray, voxel_m: float, body_m: float
) -> np.ndarray:
    """(N,) the role (index into ``eyes_xy``) whose body each of one blob's points is
    joined to. The nearest eye in the floor plane is wrong for a hand far out over the field,
    which can be nearer another person's eye than its owner's; so each role's body is the
    blob's voxels within ``body_m`` of its eye's vertical (nearest eye where two overlap), and
    every voxel goes to the body from which it is reached first through the blob's own voxels
    (a geodesic Voronoi split): a hand follows its arm back to the shoulder it hangs from.
    Without any body in the blob (a still body is static scene and the arm reaches no column),
    each point is its nearest eye's."""
    near = np.argmin(np.linalg.norm(pts[:, None, :2] - eyes_xy[None], axis=2), axis=1)
    keys, point_voxel = np.unique(vox, axis=0, return_inverse=True)
    point_voxel = point_voxel.ravel()
    n_vox, n_roles = len(keys), len(eyes_xy)
    centres = np.zeros((n_vox, 2))
    np.add.at(centres, point_voxel, pts[:, :2])
    centres /= np.bincount(point_voxel, minlength=n_vox)[:, None]
    gap = np.linalg.norm(centres[:, None] - eyes_xy[None], axis=2)
    body_role = np.argmin(gap, axis=1)
    seeds = np.nonzero(gap[np.arange(n_vox), body_role] <= body_m)[0]
    if not len(seeds):
        return near
    rows, cols, weights = [n_vox + body_role[seeds]], [seeds], [np.full(len(seeds), 1e-9)]
    # 26-neighbour edges among the blob's voxels, weighted by their length
    span = keys.max(axis=0) + 3
    flat = np.ravel_multi_index((keys + 1).T, span)
    order = np.argsort(flat)
    for off in _OFFSETS:
        nb = np.ravel_multi_index((keys + 1 + off).T, span)
        at = np.clip(np.searchsorted(flat, nb, sorter=order), 0, n_vox - 1)
        hit = flat[order[at]] == nb
        rows.append(np.nonzero(hit)[0])
        cols.append(order[at[hit]])
        weights.append(np.full(int(hit.sum()), float(np.linalg.norm(off)) * voxel_m))
    size = n_vox + n_roles  # one source node per role, joined to its body's voxels
    graph = sparse.csr_matrix(
        (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), (size, size)
    )
    _, _, source = csgraph.dijkstra(
        graph, indices=np.unique(n_vox + body_role[seeds]), min_only=True,
        return_predecessors=True,
    )  # fmt: skip
    owner = source[point_voxel] - n_vox
    return np.where(owner >= 0, owner, near)


def _distance(points_m: np.ndarray, eye_m: np.ndarray | None) -> float:
    """Median horizontal distance of the points to the eye (NaN without one)."""
    if eye_m is None:
        return float("nan")
    return float(np.median(np.linalg.norm(points_m[:, :2] - eye_m[None, :2], axis=1)))


def judge_field(
    region: Region, frames: list[np.ndarray], margins: list[np.ndarray | None],
    stamps: list[tuple[float, str]], eyes: list[dict[str, np.ndarray | None]],
    free: Freespace | None = None,
) -> tuple[list[Instant], list[Event]]:  # fmt: skip
    """One field over a case: ``frames`` each timestamp's points in ``region`` (``holds``),
    ``margins`` their margins (``SterileConfig.margin_m``; None: none), ``stamps`` each one's
    (case time, model name), ``eyes`` each one's role eyes (None: not followed then) ->
    (instants, events); ``free``: the voxels the cameras saw through at each timestamp
    (``sterile_seen.freespace``; None: not known, the seen-empty tests do not apply)."""
    bg = background(region, frames, [t for t, _ in stamps])
    rows = []
    for (t, name), pts, margin, eye in zip(stamps, frames, margins, eyes, strict=True):
        rows.append(Instant(t, name, *moving_blobs(region, bg, pts, eye, t, margin, free)))
    return rows, group_events(region.box, rows, region.config, eyes)


def group_events(
    box: SiteBox, instants: list[Instant], config: SterileConfig,
    eyes: list[dict[str, np.ndarray | None]] | None = None,
) -> list[Event]:  # fmt: skip
    """Each role's contact timestamps, consecutive (up to ``max_gap`` missed) -> events; with
    ``one_event_per_touch``, the events of one touch -> one event (``eyes``: each instant's
    role eyes, to measure a part taken over from another role against its new role's eye)."""
    roles = dict.fromkeys(b.role for i in instants for b in i.blobs)
    events = []
    for role in roles:
        rows: list[tuple[int, Instant, Blob]] = []
        for k, inst in enumerate(instants):
            mine = [b for b in inst.blobs if b.role == role]
            if mine:
                rows.append((k, inst, max(mine, key=lambda b: b.count)))
        runs: list[list[tuple[int, Instant, Blob]]] = []
        for row in rows:
            if runs and row[0] - runs[-1][-1][0] <= config.max_gap + 1:
                runs[-1].append(row)
            else:
                runs.append([row])
        for run in runs:
            events.append(
                Event(box.name, role, role in config.sterile_roles,
                      tuple(r[1] for r in run), tuple(r[2] for r in run))
            )  # fmt: skip
    if config.one_event_per_touch:
        events = _one_event_per_touch(events, instants, config, eyes)
    events = [
        e for e in events if len(e.instants) >= config.min_timestamps and _moved_in(e, config)
    ]
    return sorted(events, key=lambda e: (e.start_s, e.role))


def set_aside(
    box: SiteBox, instants: list[Instant], config: SterileConfig, found: list[Event],
    eyes: list[dict[str, np.ndarray | None]] | None = None,
) -> list[Event]:  # fmt: skip
    """The contact events test 6 (moved there) sets aside: what the same evidence gives with
    the test off and not with it on (``found``: ``group_events`` with it on). Its price is
    someone who stood at the box's face and then reached in, so what it sets aside is listed
    for the reviewer, never dropped unseen. The test only removes events after they are
    grouped, so the two lists differ by exactly those."""
    if config.max_filled_before >= 1:
        return []
    kept = {(e.role, e.start_s, e.end_s) for e in found}
    off = replace(config, max_filled_before=1.0)
    return [
        e for e in group_events(box, instants, off, eyes)
        if not e.sterile_role and (e.role, e.start_s, e.end_s) not in kept
    ]  # fmt: skip


def _moved_in(event: Event, config: SterileConfig) -> bool:
    """Whether at one of an event's timestamps at least its part crossed into the box where the
    case was empty just before (test 6), or no timestamp can say."""
    return any(not b.filled_before > config.max_filled_before for b in event.blobs)


def _one_event_per_touch(
    events: list[Event], instants: list[Instant], config: SterileConfig,
    eyes: list[dict[str, np.ndarray | None]] | None,
) -> list[Event]:  # fmt: skip
    """Events of different roles that are one touch (their in-box voxels touch at timestamps
    at most ``max_gap`` + 1 apart; the same kind: sterile or not) -> one event, named for the
    role holding the touch at the most timestamps, then the most points."""
    at = {id(inst): k for k, inst in enumerate(instants)}
    cells = [[(at[id(i)], _in_box_cells(b, config.voxel_m))
              for i, b in zip(e.instants, e.blobs, strict=True)] for e in events]  # fmt: skip
    group = list(range(len(events)))  # union-find over the events

    def root(k: int) -> int:
        while group[k] != k:
            group[k] = group[group[k]]
            k = group[k]
        return k

    for a in range(len(events)):
        for b in range(a + 1, len(events)):
            same_kind = events[a].sterile_role == events[b].sterile_role
            if (
                same_kind
                and events[a].role != events[b].role
                and _touching(cells[a], cells[b], config.max_gap + 1)
            ):
                group[root(b)] = root(a)
    out = []
    for r in dict.fromkeys(root(k) for k in range(len(events))):
        members = [e for k, e in enumerate(events) if root(k) == r]
        if len(members) == 1:
            out.append(members[0])
            continue
        keeper = max(members, key=lambda e: (len(e.instants), sum(b.count for b in e.blobs)))
        held: dict[int, Blob] = {}
        for e in sorted(members, key=lambda e: e is not keeper):  # the keeper's parts first
            for inst, blob in zip(e.instants, e.blobs, strict=True):
                k = at[id(inst)]
                if k not in held:
                    eye = eyes[k].get(keeper.role) if eyes is not None else None
                    held[k] = blob if e is keeper else Blob(
                        blob.points_m, blob.in_field, keeper.role, _distance(blob.points_m, eye),
                        blob.filled_before,
                    )  # fmt: skip
        order = sorted(held)
        out.append(Event(keeper.field, keeper.role, keeper.sterile_role,
                         tuple(instants[k] for k in order),
                         tuple(held[k] for k in order)))  # fmt: skip
    return out


def _in_box_cells(blob: Blob, voxel_m: float) -> set[tuple[int, int, int]]:
    """The world-grid voxels of a blob's in-box points."""
    idx = np.floor(blob.points_m[blob.in_field] / voxel_m).astype(int)
    return {tuple(v) for v in np.unique(idx, axis=0).tolist()}


def _touching(a: list[tuple[int, set]], b: list[tuple[int, set]], within: int) -> bool:
    """Whether two events' in-box voxels touch (26-neighbours) at timestamps ``within`` apart."""
    for ka, ca in a:
        grown = {(x + i, y + j, z + k) for x, y, z in ca for i, j, k in _NEIGHBOURHOOD}
        if any(abs(ka - kb) <= within and not grown.isdisjoint(cb) for kb, cb in b):
            return True
    return False


_NEIGHBOURHOOD = [(0, 0, 0), *map(tuple, _OFFSETS.tolist())]
