"""The report's HTML: one file, its CSS inline, every picture a ``data:`` URI, no script and
no link out, so it opens offline and prints (``@media print`` keeps a figure on one page).
Every text from a file (names, metadata, roles) is escaped by Jinja2's autoescape."""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import cv2
import jinja2
import numpy as np

from reconstructor.report.facts import CaseFacts
from reconstructor.report.reviews import SightlineReview, SterileReview
from reconstructor.report.views import RoleShare, Thumb

TEMPLATE_NAME = "report.html.j2"  # beside this module
REAL_WIDTH_PX = 320  # a real camera frame in the report: enough to tell a hand from the drape


def png_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def rgb_uri(rgb: np.ndarray, *, jpeg: bool = False, width_px: int | None = None) -> str:
    """An RGB array as a PNG (renders: exact) or JPEG (camera frames: small) data URI."""
    if width_px is not None and rgb.shape[1] > width_px:
        h = max(1, round(rgb.shape[0] * width_px / rgb.shape[1]))
        rgb = cv2.resize(rgb, (width_px, h), interpolation=cv2.INTER_AREA)
    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    params = [cv2.IMWRITE_JPEG_QUALITY, 88] if jpeg else []
    ok, buf = cv2.imencode(".jpg" if jpeg else ".png", bgr, params)
    assert ok, "OpenCV failed to encode an image"
    kind = "jpeg" if jpeg else "png"
    return f"data:image/{kind};base64," + base64.b64encode(buf.tobytes()).decode("ascii")


@dataclass
class PageInputs:
    facts: CaseFacts
    timeline_png: bytes
    sterile: SterileReview | None
    sightlines: list[SightlineReview]
    thumbs: list[Thumb]
    shares: list[RoleShare]
    share_timestamps: int
    roles_file: str | None
    event_stills: dict[int, tuple[np.ndarray, str]] = field(default_factory=dict)
    real_note: str = ""  # why the real camera panels are empty ("" when they are shown)
    command: str = ""
    generated: str = ""
    not_run: dict[str, str] = field(default_factory=dict)  # section -> the command to make it
    uncovered_times: list[float] = field(default_factory=list)  # asked, no role's eye (gaps too)


def _pct(x: float) -> str:
    return "unknown" if not math.isfinite(x) else f"{x:.0%}"


def render_page(p: PageInputs) -> str:
    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined)
    env.filters["pct"] = _pct
    env.filters["b64"] = lambda data: base64.b64encode(data).decode("ascii")
    env.filters["tod"] = p.facts.clock.time_of_day
    text = resources.files("reconstructor.report").joinpath(TEMPLATE_NAME).read_text("utf-8")
    template = env.from_string(text)
    return template.render(p=p, f=p.facts, h=p.facts.health, sight=_sight_summaries(p),
                           png_uri=png_uri, rgb_uri=rgb_uri, real_w=REAL_WIDTH_PX,
                           groups=_thumb_groups(p.thumbs))  # fmt: skip


def _thumb_groups(thumbs: list[Thumb]) -> list[tuple[float, list[Thumb]]]:
    out: dict[float, list[Thumb]] = {}
    for t in thumbs:
        out.setdefault(t.t_s, []).append(t)
    return sorted(out.items())


def _sight_summaries(p: PageInputs) -> list[dict[str, Any]]:
    out = []
    for r in p.sightlines:
        per = []
        for label in dict.fromkeys(x.position for x in r.rows):
            sel = [x for x in r.rows if x.position == label]
            vis = [x.visible for x in sel]
            per.append({
                "position": label, "min": min(vis), "max": max(vis), "n": len(sel),
                "hidden": [x.t_s for x in sel if x.visible < 0.5],
                "inferred": sum(x.rests_on_inferred for x in sel),
            })  # fmt: skip
        out.append({"review": r, "positions": per})
    return out
