"""Pictures of the simulated OR that people would rather look at than numbers: the rig's eight
views, a top-down map of the room, and a ground-truth video."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from protocol.camera import Resolution
from sim.world import World

log = logging.getLogger(__name__)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (0, 0), (8 + 9 * len(text), 24), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def rig_mosaic(
    world: World, t_s: float, resolution: str = "SVGA", tile_width_px: int = 480
) -> np.ndarray:
    """(H, W, 3) RGB: each unit's left and right view side by side, one unit per row."""
    res = Resolution.parse(resolution)
    rows = []
    for unit in world.rig:
        left, right = world.render_stereo(unit.index, t_s, res)
        tiles = []
        for side, r in (("left", left), ("right", right)):
            h = round(r.image_rgb.shape[0] * tile_width_px / r.image_rgb.shape[1])
            small = cv2.resize(r.image_rgb, (tile_width_px, h), interpolation=cv2.INTER_AREA)
            tiles.append(_label(small, f"SN{unit.serial} {side} ({unit.node_id}) t={t_s:.2f}s"))
        rows.append(np.hstack(tiles))
    return np.vstack(rows)


def depth_colour(depth_m: np.ndarray, max_m: float = 8.0) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) RGB with a perceptual colour map; black where nothing was hit."""
    d = np.where(np.isfinite(depth_m), depth_m, 0.0)
    q = np.clip(d / max_m * 255.0, 0, 255).astype(np.uint8)
    col = cv2.applyColorMap(q, cv2.COLORMAP_TURBO)[..., ::-1]
    col[~np.isfinite(depth_m)] = 0
    return np.ascontiguousarray(col)


def topdown_map(world: World, t_s: float, path: Path | str, trail_s: float = 6.0) -> Path:
    """A plan view: room, furniture, the four cameras with their fields of view, people with their
    heading and recent path, and the wand's path if there is one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon, Rectangle

    room = world.config.room
    fig, ax = plt.subplots(figsize=(9, 7.8), dpi=110)
    x0, x1 = room.x_range_m
    y0, y1 = room.y_range_m
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=2.5, color="0.2"))
    for fp in world.footprints():
        c, s = np.cos(fp.yaw_rad), np.sin(fp.yaw_rad)
        hx, hy = fp.size_xy_m[0] / 2, fp.size_xy_m[1] / 2
        corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) @ np.array(
            [[c, s], [-s, c]]
        ) + np.asarray(fp.centre_xy_m)
        ax.add_patch(Polygon(corners, closed=True, fc="0.85", ec="0.4"))
        ax.text(*fp.centre_xy_m, fp.label, ha="center", va="center", fontsize=7, color="0.25")
    colours = plt.cm.tab10(np.arange(len(world.rig)))
    for unit, col in zip(world.rig, colours, strict=True):
        cam = unit.sensor("left", Resolution.HD1200)
        c = cam.pose.centre_m
        fwd = cam.pose.R[2]
        yaw = np.arctan2(fwd[1], fwd[0])
        half = np.arctan(cam.intrinsics.width_px / 2 / cam.intrinsics.fx_px)
        reach = 2.2
        wedge = np.array(
            [c[:2]]
            + [
                c[:2] + reach * np.array([np.cos(a), np.sin(a)])
                for a in np.linspace(yaw - half, yaw + half, 12)
            ]
        )
        ax.add_patch(Polygon(wedge, closed=True, fc=(*col[:3], 0.12), ec=col, lw=1))
        ax.plot(*c[:2], marker="s", color=col, ms=9)
        ax.annotate(
            f"SN{unit.serial}\n{unit.node_id}",
            (float(c[0]), float(c[1])),
            textcoords="offset points",
            xytext=(0, -22 if c[1] > 0 else 10),
            ha="center",
            fontsize=7,
            color=col,
        )
    times = np.linspace(max(0.0, t_s - trail_s), t_s, 25)
    for k, person in enumerate(world.people(t_s)):
        trail = np.array(
            [
                next(p.position_xy_m for p in world.people(float(tt)) if p.name == person.name)
                for tt in times
            ]
        )
        col = plt.cm.Dark2(k % 8)
        ax.plot(trail[:, 0], trail[:, 1], "-", color=col, lw=1.2, alpha=0.7)
        px, py = person.position_xy_m
        ax.add_patch(plt.Circle((px, py), 0.22, color=col, alpha=0.9))
        h = person.heading_rad + person.head_yaw_rad
        ax.arrow(px, py, 0.45 * np.cos(h), 0.45 * np.sin(h), head_width=0.09, color="k", lw=1)
        ax.text(px, py + 0.3, person.name.replace("_", " "), ha="center", fontsize=7)
    if world.show_wand:
        motion = world.wand_motion
        times_wand = np.linspace(0, t_s, 200)
        path_pts = np.array([motion.sphere_centres(float(tt))[1] for tt in times_wand])
        ax.plot(path_pts[:, 0], path_pts[:, 1], "-", color="tab:orange", lw=0.8, label="wand")
        now = motion.sphere_centres(t_s)
        ax.plot(now[:, 0], now[:, 1], "o-", color="tab:orange", ms=4)
        ax.legend(loc="upper right")
    ax.set_xlim(x0 - 0.3, x1 + 0.3)
    ax.set_ylim(y0 - 0.3, y1 + 0.3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m), head end of the table at -x")
    ax.set_ylabel("y (m)")
    ax.set_title(
        f"Simulated OR, phase '{world.config.phase}', seed {world.config.seed}, t = {t_s:.2f} s"
    )
    ax.grid(alpha=0.25)
    out = Path(path)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def ground_truth_video(
    world: World,
    path: Path | str,
    t_start_s: float,
    t_end_s: float,
    fps: float = 10.0,
    person: str | None = "surgeon",
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """An MP4 of ground truth over time: a rig camera's view, its true depth, and one person's
    egocentric view (the view EgoSurg has to synthesise)."""
    times = np.arange(t_start_s, t_end_s, 1.0 / fps)
    if len(times) == 0:
        raise ValueError("the video's time range holds no frame: make t_end_s > t_start_s")
    out = Path(path)
    writer: cv2.VideoWriter | None = None
    try:
        for k, t in enumerate(times):
            frame = _video_frame(world, float(t), person)
            if writer is None:
                h, w = frame.shape[:2]
                fourcc = cv2.VideoWriter_fourcc(*"mp4v")  # type: ignore[attr-defined]
                writer = cv2.VideoWriter(str(out), fourcc, fps, (w, h))
                if not writer.isOpened():
                    raise OSError(f"cannot write video {out}: OpenCV has no MP4 encoder here")
            writer.write(np.ascontiguousarray(frame[..., ::-1]))
            if progress:
                progress(k + 1, len(times))
    finally:
        if writer is not None:
            writer.release()
    return out


def _video_frame(world: World, t: float, person: str | None) -> np.ndarray:
    left = world.render_sensor(0, "left", t, Resolution.SVGA)
    tile_w, tile_h = 640, 400
    rig = cv2.resize(left.image_rgb, (tile_w, tile_h), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(
        depth_colour(left.depth_m), (tile_w, tile_h), interpolation=cv2.INTER_NEAREST
    )
    tiles = [_label(rig, f"SN{world.rig[0].serial} left, t={t:.2f}s"), _label(depth, "true depth")]
    heads = world.head_poses(t)
    if heads:
        name = person if person in heads else sorted(heads)[0]
        cam = world.virtual_camera(heads[name], hfov_deg=90, size_px=(tile_w, tile_h), name=name)
        tiles.append(_label(world.render(cam, t).image_rgb, f"egocentric: {name}"))
    return np.hstack(tiles)
