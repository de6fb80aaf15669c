"""Named boxes of a site (``egosurg-site``): targets for line of sight, fields for sterility.

A site file names fixed things in the room's world frame that reviewers ask questions about: a
monitor's screen, the drape, the back table. ``egosurg sim roles --site-out`` writes the
simulator's true boxes; a real site measures them once.

Format (version 1)::

    format = "egosurg-site"
    format_version = 1
    [session]                        # the session it was made for (optional; see below)
    name = "sim-intraoperative-seed3"
    started_unix_ns = 1767225600000000000
    [[boxes]]
    name = "monitor-a"
    centre_m = [1.735, -1.372, 1.75]
    size_m = [0.008, 0.58, 0.36]     # along the box's own x, y, z
    yaw_deg = 143.2                  # the box's x axis, turned about world +z from world +x
    front_only = true                # only the +x face counts (a screen seen from behind: 0)

``[session]`` names the recording the boxes were measured for (``protocol/formats/
session_id.py``): a field or target box placed for one session's room and table need not fit
another's, so the review commands refuse a file made for another session than the case's and
warn about one without the table (a site measured once, by hand, for every session).

Each box's surface is sampled on a fixed grid (:func:`surface_points`); a viewer sees the
faces whose outward normal points towards the eye, so a solid box seen from anywhere can be
fully visible and "fraction visible" means of what faces the viewer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.errors import UserError
from protocol.formats.session_id import SessionId, session_toml_lines
from protocol.toml_config import load_toml, read_table

SITE_FORMAT = "egosurg-site"
SITE_FORMAT_VERSION = 1


class SiteFileError(UserError, ValueError):
    """A site file that cannot be used; the message names the box and the fix."""


@dataclass(frozen=True, kw_only=True)
class SiteBox:
    name: str
    centre_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_deg: float = 0.0
    front_only: bool = False

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("a box needs a name")
        if not (np.all(np.isfinite(self.centre_m)) and np.all(np.asarray(self.size_m) > 0)):
            raise ValueError(f"box {self.name!r}: centre_m finite and size_m positive, please")
        if not math.isfinite(self.yaw_deg):
            raise ValueError(f"box {self.name!r}: yaw_deg must be finite")

    @property
    def rotation(self) -> np.ndarray:
        """World-from-box rotation."""
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def contains(self, points_m: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        local = (np.asarray(points_m) - np.asarray(self.centre_m)) @ self.rotation
        return np.all(np.abs(local) <= np.asarray(self.size_m) / 2 + margin_m, axis=-1)


def surface_points(box: SiteBox, eye_m: np.ndarray, per_face: int = 12) -> np.ndarray:
    """(N, 3) world points on the faces of ``box`` that face ``eye_m`` (a ``per_face`` x
    ``per_face`` grid of cell centres each); empty when no counted face faces the eye."""
    R, c, half = box.rotation, np.asarray(box.centre_m, float), np.asarray(box.size_m) / 2
    eye_local = (np.asarray(eye_m, float) - c) @ R
    u = (np.arange(per_face) + 0.5) / per_face * 2 - 1  # cell centres in (-1, 1)
    a, b = (g.ravel() for g in np.meshgrid(u, u, indexing="ij"))
    faces = [(0, 1.0)] if box.front_only else [(ax, sg) for ax in range(3) for sg in (1.0, -1.0)]
    out = []
    for axis, sign in faces:
        if sign * eye_local[axis] <= half[axis]:  # the eye is not in front of this face
            continue
        o1, o2 = [k for k in range(3) if k != axis]
        pts = np.zeros((a.size, 3))
        pts[:, axis] = sign * half[axis]
        pts[:, o1], pts[:, o2] = a * half[o1], b * half[o2]
        out.append(pts)
    if not out:
        return np.zeros((0, 3))
    return np.concatenate(out) @ R.T + c


@dataclass(frozen=True, kw_only=True)
class SiteFile:
    format: str
    format_version: int
    session: SessionId | None = None  # the session it was made for; None: not recorded
    boxes: tuple[SiteBox, ...] = ()


def read_site(path: Path | str) -> dict[str, SiteBox]:
    """The file's boxes by name; every problem is a :class:`SiteFileError`."""
    return read_site_file(path)[1]


def read_site_file(path: Path | str) -> tuple[SessionId | None, dict[str, SiteBox]]:
    """(the session the file names or None, its boxes by name)."""
    path = Path(path)
    if not path.exists():
        raise SiteFileError(f"the site file {path} does not exist")
    table, _ = load_toml(path, "the site file", error=SiteFileError)
    if table.get("format") != SITE_FORMAT or table.get("format_version") != SITE_FORMAT_VERSION:
        raise SiteFileError(
            f'{path} is not a site file: it needs format = "{SITE_FORMAT}" and format_version = '
            f"{SITE_FORMAT_VERSION} (docs/replay.md has an example)"
        )
    boxes: dict[str, SiteBox] = {}
    file = read_table(SiteFile, table, str(path), error=SiteFileError)
    for box in file.boxes:
        if box.name in boxes:
            raise SiteFileError(f"{path}: the box name {box.name!r} repeats")
        boxes[box.name] = box
    if not boxes:
        raise SiteFileError(f"{path} holds no [[boxes]]")
    return file.session, boxes


def site_toml(boxes: list[SiteBox], session: SessionId | None = None) -> str:
    """The file's text; ``session``: the session it is made for (its ``[session]`` table)."""
    lines = [f'format = "{SITE_FORMAT}"', f"format_version = {SITE_FORMAT_VERSION}"]
    lines += session_toml_lines(session)
    for b in boxes:
        lines += [
            "",
            "[[boxes]]",
            f'name = "{b.name}"',
            "centre_m = [" + ", ".join(f"{v:.4f}" for v in b.centre_m) + "]",
            "size_m = [" + ", ".join(f"{v:.4f}" for v in b.size_m) + "]",
            f"yaw_deg = {b.yaw_deg:.4f}",
            f"front_only = {'true' if b.front_only else 'false'}",
        ]
    return "\n".join(lines) + "\n"
