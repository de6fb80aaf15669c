"""Frames to an H.264 MP4 (PyAV, through its bundled FFmpeg), a burned-in time code, and a
picture-in-picture of the nearest real camera."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np

from reconstructor.errors import VideoOutputError


class Mp4Writer:
    """``write(rgb)`` appends one (H, W, 3) uint8 RGB frame; H.264, yuv420p (what every player
    reads), so width and height must be even."""

    def __init__(self, path: Path | str, size_px: tuple[int, int], fps: float) -> None:
        w, h = size_px
        if w % 2 or h % 2:
            raise VideoOutputError(f"--size {w}x{h}: H.264 needs an even width and height")
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._container = av.open(str(self.path), mode="w")
        except (OSError, av.error.FFmpegError) as exc:
            raise VideoOutputError(f"cannot write {self.path}: {exc}") from None
        self._stream = self._container.add_stream(
            "libx264", rate=Fraction(fps).limit_denominator(1000)
        )
        self._stream.width, self._stream.height = w, h
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": "20", "preset": "veryfast"}
        self.frames = 0

    def write(self, rgb: np.ndarray) -> None:
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def burn_text(rgb: np.ndarray, lines: list[str]) -> np.ndarray:
    """White text on a dark band at the top left, scaled to the image (smaller where the
    longest line would not fit its width)."""
    out = np.ascontiguousarray(rgb)
    scale = max(0.35, out.shape[1] / 1600)
    thick = max(1, round(scale * 2))
    widest = max((cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)[0][0] for t in lines),
                 default=0)  # fmt: skip
    if widest > out.shape[1] - 4:
        scale = max(0.25, scale * (out.shape[1] - 4) / widest)
        thick = max(1, round(scale * 2))
    y = 0
    for text in lines:
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
        pad = max(2, th // 3)
        y += th + 2 * pad
        cv2.rectangle(out, (0, y - th - 2 * pad), (tw + 2 * pad, y + base - pad), (0, 0, 0), -1)
        cv2.putText(out, text, (pad, y - pad), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255),
                    thick, cv2.LINE_AA)  # fmt: skip
    return out


def timecode(t_s: float) -> str:
    """``HH:MM:SS.mmm`` of case time."""
    ms = round(t_s * 1000)
    h, rem = divmod(ms, 3_600_000)
    m, rem = divmod(rem, 60_000)
    s, ms = divmod(rem, 1000)
    return f"{h:02d}:{m:02d}:{s:02d}.{ms:03d}"


def seconds_span(start_s: float, end_s: float) -> str:
    """``6.320-7.280 s``, or ``at 7.000 s`` when both read the same: something seen at one
    timestamp happened at one time, not over a span that starts where it ends."""
    a, b = f"{start_s:.3f}", f"{end_s:.3f}"
    return f"at {a} s" if a == b else f"{a}-{b} s"


def timecode_span(start_s: float, end_s: float) -> str:
    """``00:00:06.320 - 00:00:07.280``, or ``at 00:00:07.000`` for one time (``seconds_span``)."""
    a, b = timecode(start_s), timecode(end_s)
    return f"at {a}" if a == b else f"{a} - {b}"


def paste_pip(rgb: np.ndarray, inset_rgb: np.ndarray, label: str, fraction: float = 0.3):
    """``inset_rgb`` scaled to ``fraction`` of the width, framed, at the bottom right."""
    out = np.ascontiguousarray(rgb)
    h, w = out.shape[:2]
    iw = max(8, int(w * fraction))
    ih = max(8, round(inset_rgb.shape[0] * iw / inset_rgb.shape[1]))
    if ih >= h:
        return out
    small = cv2.resize(inset_rgb, (iw, ih), interpolation=cv2.INTER_AREA)
    small = burn_text(small, [label])
    x0, y0 = w - iw - 4, h - ih - 4
    cv2.rectangle(out, (x0 - 2, y0 - 2), (x0 + iw + 1, y0 + ih + 1), (255, 255, 255), 2)
    out[y0 : y0 + ih, x0 : x0 + iw] = small
    return out
