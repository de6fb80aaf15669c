"""Sterile-field contact: when reconstructed things that are not part of the static scene enter a
field box (the drape, the back table), grouped into events, each with the nearest role.

**Static scene.** Each timestamp of a case is reconstructed on its own, so the same drape is
made of different Gaussians each time; what stays is where they are. The region around the
field (the box grown by ``reach_m``) is cut into ``voxel_m`` voxels; a voxel holding a Gaussian
(opacity at least ``min_opacity``) at ``static_fraction`` or more of the case's timestamps is
the static scene (a per-voxel median over time, the classic background model of fixed
cameras), grown by one voxel so that a surface's jitter between reconstructions is not motion.
This needs no empty-room recording; its price: something that stays in the field for more than
``static_fraction`` of the case becomes background (use a shorter ``--from``/``--to`` span).

**Contacts.** At each timestamp the other occupied voxels are the moving things. They are
split into 26-connected blobs over the whole region, so that a hand in the field stays joined
to its arm and body outside it; a blob with at least ``min_gaussians`` Gaussians inside the box
touches the field if it also reaches out of the box by ``min_outside`` Gaussians: someone
reaching in is joined to the arm outside, while a blob wholly inside is a floater or a
surface's jitter (the price: a thing dropped into the field alone is not a contact). A blob's
role is the majority of its Gaussians' nearest role (horizontal distance to the role's eye),
so the body decides, not the hand alone; a blob whose Gaussians lie a median of more than
``max_role_distance_m`` from every role's eye is nobody's arm (a surface's noise) and is
dropped when roles are given. Blobs of
``sterile_roles`` (the gowned team, whose work in the field is not a contact) are kept apart.

**Events.** A role's consecutive contact timestamps form one event (``max_gap`` missed
timestamps inside it are bridged); its start is its first contact timestamp, so it is late by
at most the case's sampling interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from protocol.site import SiteBox
from reconstructor.errors import ReconstructError


class SterileError(ReconstructError, ValueError):
    pass


@dataclass(frozen=True, kw_only=True)
class SterileConfig:
    voxel_m: float = 0.05  # a hand is about two voxels across
    reach_m: float = 0.8  # blobs are traced this far around the box: an arm and a shoulder
    static_fraction: float = 0.5  # occupied at least this often: the static scene
    min_opacity: float = 0.05  # fainter: pruned floaters (a fresh Gaussian starts at 0.1)
    min_gaussians: int = 8  # Gaussians of one blob inside the box for a contact
    min_outside: int = 3  # and outside it: the arm that reaches in (a lone blob is a floater)
    max_gap: int = 1  # missed timestamps bridged inside one event
    max_role_distance_m: float = 0.4  # a blob farther from every role is no one's arm
    min_timestamps: int = 1  # 2 drops one-timestamp noise, and touches shorter than 2 intervals
    sterile_roles: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not (0.01 <= self.voxel_m <= 0.5 and 0 <= self.reach_m <= 3):
            raise ValueError(f"voxel_m {self.voxel_m} (0.01-0.5) or reach_m {self.reach_m} (0-3)")
        if not 0 < self.static_fraction <= 1:
            raise ValueError(f"static_fraction {self.static_fraction}: give (0, 1]")
        if not (0 <= self.min_opacity < 1 and self.min_gaussians >= 1 and self.max_gap >= 0):
            raise ValueError("min_opacity in [0, 1), min_gaussians >= 1, max_gap >= 0, please")
        if self.min_timestamps < 1 or not self.max_role_distance_m > 0:
            raise ValueError("min_timestamps >= 1 and max_role_distance_m > 0, please")


@dataclass(frozen=True)
class Blob:
    """A moving thing that touches the field at one timestamp."""

    points_m: np.ndarray  # (N, 3) its Gaussians' centres, all of the blob
    in_field: np.ndarray  # (N,) bool: inside the box
    role: str  # "" without roles
    role_distance_m: float  # median horizontal distance of its Gaussians to the role's eye

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
    moving_in_field: int  # moving Gaussians inside the box, all blobs
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
        return points_m[np.all(np.abs(self.local(points_m)) < self.half_m, axis=1)]

    def voxels(self, points_m: np.ndarray) -> np.ndarray:
        """(N, 3) int voxel indices of points inside the region."""
        idx = np.floor((self.local(points_m) + self.half_m) / self.config.voxel_m).astype(int)
        return np.clip(idx, 0, np.asarray(self.shape) - 1)

    def occupancy(self, points_m: np.ndarray) -> np.ndarray:
        grid = np.zeros(self.shape, bool)
        v = self.voxels(points_m)
        grid[v[:, 0], v[:, 1], v[:, 2]] = True
        return grid


def static_scene(region: Region, frames: list[np.ndarray]) -> np.ndarray:
    """(X, Y, Z) bool: voxels occupied in at least ``static_fraction`` of ``frames`` (each a
    timestamp's points in the region), grown by one voxel."""
    counts = np.zeros(region.shape, np.int32)
    for pts in frames:
        counts += region.occupancy(pts)
    static = counts >= region.config.static_fraction * len(frames)
    return ndimage.binary_dilation(static, structure=np.ones((3, 3, 3), bool))


def moving_blobs(
    region: Region, static: np.ndarray, points_m: np.ndarray, eyes_m: dict[str, np.ndarray]
) -> tuple[int, list[Blob]]:
    """(moving Gaussians inside the box, the moving blobs that touch the box) at one timestamp.
    ``eyes_m``: each role's eye then (empty: no roles)."""
    cfg = region.config
    v = region.voxels(points_m)
    moving = ~static[v[:, 0], v[:, 1], v[:, 2]]
    pts, v = points_m[moving], v[moving]
    inside = region.box.contains(pts)
    grid = np.zeros(region.shape, bool)
    grid[v[:, 0], v[:, 1], v[:, 2]] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    point_label = labels[v[:, 0], v[:, 1], v[:, 2]]
    blobs = []
    for k in np.unique(point_label[inside]) if n else []:
        sel = point_label == k
        n_in = int((sel & inside).sum())
        if n_in < cfg.min_gaussians or int(sel.sum()) - n_in < cfg.min_outside:
            continue
        role, dist = nearest_role(pts[sel], eyes_m)
        if eyes_m and dist > cfg.max_role_distance_m:
            continue  # a body is within ~0.3 m of its eye's vertical, a reach adds an arm
        blobs.append(Blob(pts[sel], inside[sel], role, dist))
    return int(inside.sum()), blobs


def nearest_role(points_m: np.ndarray, eyes_m: dict[str, np.ndarray]) -> tuple[str, float]:
    """The role most of the points are nearest to (horizontally, to the eye: people stand),
    and the points' median horizontal distance to that role's eye."""
    if not eyes_m:
        return "", float("nan")
    names = list(eyes_m)
    eyes = np.stack([eyes_m[n][:2] for n in names])
    d = np.linalg.norm(points_m[:, None, :2] - eyes[None], axis=2)
    votes = np.bincount(np.argmin(d, axis=1), minlength=len(names))
    best = int(np.argmax(votes))
    return names[best], float(np.median(d[:, best]))


def group_events(box: SiteBox, instants: list[Instant], config: SterileConfig) -> list[Event]:
    """Each role's contact timestamps, consecutive (up to ``max_gap`` missed) -> events."""
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
        for run in (r for r in runs if len(r) >= config.min_timestamps):
            events.append(
                Event(box.name, role, role in config.sterile_roles,
                      tuple(r[1] for r in run), tuple(r[2] for r in run))
            )  # fmt: skip
    return sorted(events, key=lambda e: (e.start_s, e.role))
