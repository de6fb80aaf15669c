"""Top-down plans of the room: where the viewer, the target, the people and the rig stood, so a
line-of-sight answer or a sterile-field event can be read without knowing the room's axes.

The outline is the rig's extent (its cameras hang at the room's walls and corners): the box
around the left cameras' positions, drawn as a dashed line and each camera as a small triangle.
Site and field boxes are drawn as their rotated footprints, people (from the roles file) as dots
with their role's name. ``who_blocks`` says which people stand on a line of sight, from the
roles file alone: a person is a standing cylinder (``PERSON_RADIUS_M`` around their eye, from
the floor to just above it), and a blocked sample point of the target is theirs where the ray
from the eye to it passes through that cylinder. A blocked point no person explains is
"something else" (equipment, or the model's own noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.formats.site import SiteBox

PERSON_RADIUS_M = 0.3  # shoulders and arms around the eye, seen from above
PERSON_TOP_M = 0.2  # the top of the head above the eye
OTHER = "something else"  # blocked, and on no person's line: equipment or model noise
TURNED_AWAY = "turned away"  # a screen whose face (front_only) does not face the eye


@dataclass
class PlanItems:
    """What one plan shows; every position in metres, world frame (z up; the plan drops z)."""

    title: str
    caption: str = ""
    cameras_m: np.ndarray | None = None  # (N, 3) the rig's left cameras
    boxes: list[tuple[SiteBox, str]] = field(default_factory=list)  # (box, matplotlib colour)
    people: dict[str, np.ndarray] = field(default_factory=dict)  # role -> eye
    circled: list[str] = field(default_factory=list)  # roles circled in red: who blocks, touched
    lines: list[tuple[np.ndarray, np.ndarray, str, str]] = field(default_factory=list)
    # (where, matplotlib marker, colour, legend label)
    marks: list[tuple[np.ndarray, str, str, str]] = field(default_factory=list)
    facing: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (eye, forward)


def who_blocks(
    eye_m: np.ndarray, points_m: np.ndarray, blocked: np.ndarray, people: dict[str, np.ndarray]
) -> dict[str, float]:
    """{role: fraction of all the target's sample points whose line from ``eye_m`` passes through
    that person, among the ``blocked`` ones}, and ``OTHER`` for blocked points no person is on;
    largest first. Empty when nothing is blocked. ``people``: the other roles' eyes (not the
    viewer's own)."""
    eye = np.asarray(eye_m, float)
    pts = np.asarray(points_m, float)[np.asarray(blocked, bool)]
    n_all = max(len(blocked), 1)
    if len(pts) == 0:
        return {}
    explained = np.zeros(len(pts), bool)
    shares: dict[str, float] = {}
    for role, head in people.items():
        on = _through_person(eye, pts, np.asarray(head, float))
        if on.any():
            shares[role] = float(on.sum()) / n_all
        explained |= on
    if (~explained).any():
        shares[OTHER] = float((~explained).sum()) / n_all
    return dict(sorted(shares.items(), key=lambda kv: -kv[1]))


def _through_person(eye: np.ndarray, pts: np.ndarray, head: np.ndarray) -> np.ndarray:
    """For each segment eye -> pts[k]: does it pass through the standing cylinder at ``head``?"""
    d = pts - eye  # (N, 3)
    dxy = d[:, :2]
    rel = head[:2] - eye[:2]
    denom = np.maximum((dxy**2).sum(axis=1), 1e-12)
    s = np.clip((dxy @ rel) / denom, 0.0, 1.0)  # nearest approach along the segment, in plan
    gap = np.linalg.norm(eye[:2] + s[:, None] * dxy - head[:2], axis=1)
    z = eye[2] + s * d[:, 2]
    return (gap < PERSON_RADIUS_M) & (z <= head[2] + PERSON_TOP_M) & (s > 0.0) & (s < 1.0)


def describe_blockers(shares: dict[str, float], target: str) -> str:
    """``no obstruction``, or ``blocked by circulator (55% of monitor-a), something else (9%)``."""
    if not shares:
        return "no obstruction"
    if TURNED_AWAY in shares:
        return f"{target}'s face is turned away from the viewer"
    parts = [f"{role} ({share:.0%} of {target})" if k == 0 else f"{role} ({share:.0%})"
             for k, (role, share) in enumerate(shares.items())]  # fmt: skip
    return "blocked by " + ", ".join(parts)


def _footprint(box: SiteBox) -> np.ndarray:
    """(5, 2) the box's outline seen from above, closed."""
    half = np.asarray(box.size_m[:2]) / 2
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * half
    R = box.rotation[:2, :2]
    return corners @ R.T + np.asarray(box.centre_m[:2])


def plan_picture(items: PlanItems, size_px: tuple[int, int] = (480, 420)) -> np.ndarray:
    """The plan as an (H, W, 3) uint8 RGB image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dpi = 100
    fig, ax = plt.subplots(figsize=(size_px[0] / dpi, size_px[1] / dpi), dpi=dpi)
    xy: list[np.ndarray] = []
    if items.cameras_m is not None and len(items.cameras_m):
        cams = np.asarray(items.cameras_m)[:, :2]
        lo, hi = cams.min(axis=0) - 0.2, cams.max(axis=0) + 0.2
        ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]],
                "--", color="0.5", lw=1, label="rig's extent")  # fmt: skip
        ax.plot(cams[:, 0], cams[:, 1], "v", color="0.35", ms=5, label="rig cameras")
        xy += [lo, hi]
    for box, colour in items.boxes:
        fp = _footprint(box)
        ax.fill(fp[:, 0], fp[:, 1], color=colour, alpha=0.25, lw=0)
        ax.plot(fp[:, 0], fp[:, 1], color=colour, lw=1.2)
        mid = fp[:4].mean(axis=0)
        ax.annotate(box.name, (float(mid[0]), float(mid[1])), fontsize=7, ha="center", va="center")
        xy.append(fp)
    for role, eye in items.people.items():
        blocking = role in items.circled
        ax.plot(eye[0], eye[1], "o", color="C3" if blocking else "0.3", ms=6 if blocking else 4)
        if blocking:
            at = (float(eye[0]), float(eye[1]))
            circle = plt.Circle(at, PERSON_RADIUS_M, fill=False, color="C3", lw=1.5)
            ax.add_patch(circle)
        ax.annotate(role, (float(eye[0]), float(eye[1])), xytext=(4, 4),
                    textcoords="offset points", fontsize=7,
                    color="C3" if blocking else "0.2")  # fmt: skip
        xy.append(np.asarray(eye[:2])[None])
    for a, b, colour, label in items.lines:
        ax.plot([a[0], b[0]], [a[1], b[1]], "-", color=colour, lw=2, label=label or None)
        xy += [np.asarray(a[:2])[None], np.asarray(b[:2])[None]]
    for where, marker, colour, label in items.marks:
        ax.plot(where[0], where[1], marker, color=colour, ms=9, label=label or None)
        xy.append(np.asarray(where[:2])[None])
    for k, (eye, forward) in enumerate(items.facing):
        d = np.asarray(forward[:2], float)
        d = 0.6 * d / max(float(np.linalg.norm(d)), 1e-9)
        ax.annotate("", xy=(float(eye[0] + d[0]), float(eye[1] + d[1])),
                    xytext=(float(eye[0]), float(eye[1])),
                    arrowprops={"arrowstyle": "->", "color": "C0", "lw": 1.5})  # fmt: skip
        if k == 0:
            ax.plot([], [], "-", color="C0", lw=1.5, label="where they faced")
    if xy:
        pts = np.concatenate([np.atleast_2d(p) for p in xy])
        lo, hi = pts.min(axis=0) - 0.4, pts.max(axis=0) + 0.4
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_title(items.title, fontsize=8)
    ax.set_xlabel(items.caption + "\n(seen from above; metres)", fontsize=7)
    ax.tick_params(labelsize=6)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.03, 1.0), framealpha=0.8)
    # the plan on the left, its legend in the right third (tight_layout leaves a legend
    # outside the axes out, and would cut it)
    fig.subplots_adjust(left=0.1, right=0.63, top=0.92, bottom=0.24)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy()  # type: ignore[attr-defined]
    plt.close(fig)
    return rgb
