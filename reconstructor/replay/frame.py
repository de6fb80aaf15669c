"""What a rendered picture carries for a team to read it: "no data" in a colour of its own with
a legend, and the real cameras large beside the render.

**No data.** The rasterizer blends the Gaussians over a background; over black, a pixel no
Gaussian covers is black, the same as a dark drape or a shadow. So the renders composite the
model over a hatch of magenta and dark grey that nothing in an operating room looks like:
``rgb + (1 - alpha) * hatch`` (the render over black is already multiplied by its alpha), so a
pixel half covered is half hatch. A legend in the bottom left says what it means.

**Real cameras.** ``grid_layout`` puts a 2 x 2 grid of the rig's left images at the frame's
time beside the render, each as large as a quarter of the render (``egosurg replay --layout
grid``); the cells are letterboxed, never stretched.
"""

from __future__ import annotations

import cv2
import numpy as np

from reconstructor.replay.video import burn_text

NO_DATA_RGB = (230, 0, 200)  # magenta: no surgical drape, gown, skin or screen looks like it
NO_DATA_DARK_RGB = (60, 60, 60)
NO_DATA_TEXT = "no data: no camera saw this"
_HATCH_PX = 6  # stripe width, px


def no_data_hatch(height: int, width: int) -> np.ndarray:
    """(H, W, 3) uint8: diagonal stripes of ``NO_DATA_RGB`` and ``NO_DATA_DARK_RGB``."""
    v, u = np.mgrid[:height, :width]
    stripe = ((u + v) // _HATCH_PX) % 2 == 0
    out = np.empty((height, width, 3), np.uint8)
    out[stripe] = NO_DATA_RGB
    out[~stripe] = NO_DATA_DARK_RGB
    return out


def show_no_data(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The render over black (``rgb``, (H, W, 3) uint8) and its coverage (``alpha``, (H, W) in
    [0, 1]) composited over the no-data hatch instead."""
    h, w = alpha.shape
    cover = np.clip(alpha, 0.0, 1.0)[:, :, None].astype(np.float32)
    out = rgb.astype(np.float32) + (1.0 - cover) * no_data_hatch(h, w).astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def no_data_legend(rgb: np.ndarray) -> np.ndarray:
    """A swatch of the hatch and ``NO_DATA_TEXT`` on a dark band at the bottom left."""
    out = np.ascontiguousarray(rgb)
    h, w = out.shape[:2]
    scale = max(0.35, w / 1600)
    thick = max(1, round(scale * 2))
    (tw, th), base = cv2.getTextSize(NO_DATA_TEXT, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    pad = max(2, th // 3)
    sw = th + 2 * pad  # a square swatch as tall as the band
    band_h = th + base + 2 * pad
    y0 = h - band_h
    if y0 <= 0 or sw + tw + 3 * pad > w:
        return out
    cv2.rectangle(out, (0, y0), (sw + tw + 3 * pad, h - 1), (0, 0, 0), -1)
    out[y0 + pad : h - pad, pad : pad + sw] = no_data_hatch(band_h - 2 * pad, sw)
    cv2.putText(out, NO_DATA_TEXT, (sw + 2 * pad, h - base - pad), cv2.FONT_HERSHEY_SIMPLEX,
                scale, (255, 255, 255), thick, cv2.LINE_AA)  # fmt: skip
    return out


def fit_into(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` scaled to fit ``width`` x ``height``, centred on black (letterboxed)."""
    out = np.zeros((height, width, 3), np.uint8)
    ih, iw = image.shape[:2]
    s = min(width / iw, height / ih)
    nw, nh = max(1, round(iw * s)), max(1, round(ih * s))
    small = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
    x0, y0 = (width - nw) // 2, (height - nh) // 2
    out[y0 : y0 + nh, x0 : x0 + nw] = small
    return out


def grid_cell(image: np.ndarray | None, label: str, width: int, height: int) -> np.ndarray:
    """One camera's cell: its image letterboxed with its label, or a grey cell saying why not."""
    if image is None:
        cell = np.full((height, width, 3), 40, np.uint8)
    else:
        cell = fit_into(image, width, height)
    cell = burn_text(cell, [label])
    cv2.rectangle(cell, (0, 0), (width - 1, height - 1), (255, 255, 255), 1)
    return cell


def grid_layout(render: np.ndarray, cells: list[tuple[np.ndarray | None, str]]) -> np.ndarray:
    """``render`` (H, W, 3) on the left, up to four cameras in a 2 x 2 grid (each W/2 x H/2) on
    the right: (H, 2W, 3)."""
    h, w = render.shape[:2]
    cw, ch = w // 2, h // 2
    right = np.zeros((h, w, 3), np.uint8)
    for k, (image, label) in enumerate(cells[:4]):
        r, c = divmod(k, 2)
        right[r * ch : (r + 1) * ch, c * cw : (c + 1) * cw] = grid_cell(image, label, cw, ch)
    return np.concatenate([render, right], axis=1)
