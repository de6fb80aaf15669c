"""Observed versus inferred over a case (``reconstructor.replay.observed`` has the measure):
each model's view counts, made once from the cameras its run saved, and the two uses of them.

- ``egosurg replay ... --observed``: beside ``OUT.mp4``, ``OUT.observed.mp4`` (the same frames
  with inferred content tinted magenta and the frame's observed share burned in) and
  ``OUT.observed.csv`` (per frame: time, model, observed share, flag when under
  ``well_observed_share``).
- ``egosurg sightline``: per instant the observed share of the target's sampled pixels, as the
  aimed camera shows them (the target, or what hides it); under ``well_observed_share`` the
  answer rests on inferred content and the CSV flags it.
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path
from typing import Any

import numpy as np

from protocol.camera import Camera
from reconstructor.case.index import Entry
from reconstructor.errors import ObservedError
from reconstructor.raster import RasterConfig
from reconstructor.replay.observed import (
    ObservedConfig,
    ObservedRender,
    observation_counts,
    observed_map,
    overlay,
    run_input_cameras,
)
from reconstructor.replay.video import Mp4Writer, burn_text, timecode
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)


class CaseObserved:
    """View counts of a case's models, by entry, each made the first time it is asked for.

    ``count_raster`` is the models' own raster settings (the input cameras' near plane, not a
    viewer's eye)."""

    def __init__(
        self, folder: Path, count_raster: RasterConfig, config: ObservedConfig | None = None
    ) -> None:
        self.folder = Path(folder)
        self.count_raster = count_raster
        self.config = config or ObservedConfig()
        self._counts: dict[str, np.ndarray] = {}
        self._warned: set[str] = set()

    def counts(self, entry: Entry, g: Gaussians) -> np.ndarray:
        if entry.name not in self._counts:
            cameras = run_input_cameras(self.folder / "runs" / entry.name)
            self._counts[entry.name] = observation_counts(
                g, cameras, self.count_raster, self.config
            )
        return self._counts[entry.name]

    def render(
        self, entry: Entry, g: Gaussians, camera: Camera, raster: RasterConfig
    ) -> ObservedRender:
        return observed_map(g, self.counts(entry, g), camera, raster, self.config)

    def target_share(
        self, entry: Entry, g: Gaussians, details: dict[str, Any], raster: RasterConfig
    ) -> float:
        """The observed share at a sightline target's sampled pixels (``details`` from
        ``sightline.visible_fraction``: its aimed camera and the points' pixels); NaN when no
        face of the target faced the eye (nothing was sampled)."""
        if "camera" not in details:
            return float("nan")
        try:
            obs = self.render(entry, g, details["camera"], raster).observed
        except ObservedError as exc:  # the sightline answer stands; its support is unknown
            if entry.name not in self._warned:
                self._warned.add(entry.name)
                log.warning("%s: observed share unknown (flagged): %s", entry.name, exc)
            return float("nan")
        u, v = details["pixels"][:, 0], details["pixels"][:, 1]
        return float(obs[v, u].mean())

    def rests_on_inferred(self, share: float) -> bool:
        """Under ``well_observed_share``, or unknown (NaN): nothing vouches for it."""
        return not share >= self.config.well_observed_share


def observed_paths(out: Path) -> tuple[Path, Path]:
    """``OUT.observed.mp4`` and ``OUT.observed.csv`` beside a replay's ``OUT.mp4``."""
    return out.with_suffix(".observed.mp4"), out.with_suffix(".observed.csv")


class ReplayObserved:
    """The ``--observed`` outputs of a replay; a context manager that removes both files when
    the replay fails (never half a video that looks whole). Disabled, it does nothing."""

    def __init__(
        self,
        folder: Path,
        out: Path,
        size_px: tuple[int, int],
        fps: float,
        count_raster: RasterConfig,
        *,
        enabled: bool,
        config: ObservedConfig | None = None,
    ) -> None:
        self.enabled = enabled
        self.case = CaseObserved(folder, count_raster, config)
        self.video_path, self.csv_path = observed_paths(out)
        self._size, self._fps = size_px, fps
        self._video: Mp4Writer | None = None
        self._rows: list[tuple[float, str, float, bool]] = []

    def __enter__(self) -> ReplayObserved:
        if self.enabled:
            self._video = Mp4Writer(self.video_path, self._size, self._fps)
        return self

    def add(
        self, t_s: float, entry: Entry, g: Gaussians, camera: Camera, rgb: np.ndarray,
        raster: RasterConfig,
    ) -> None:  # fmt: skip
        """One frame: ``rgb`` is the plain render of ``camera`` at ``t_s``."""
        if self._video is None:
            return
        obs = self.case.render(entry, g, camera, raster)
        flagged = self.case.rests_on_inferred(obs.share)
        lines = [
            f"{timecode(t_s)}  observed {obs.share:.2f}" + ("  INFERRED" if flagged else ""),
            f"magenta: seen by fewer than {self.case.config.min_views} real cameras",
        ]
        self._video.write(burn_text(overlay(rgb, obs.observed), lines))
        self._rows.append((t_s, entry.name, obs.share, flagged))

    def card(self, shown: np.ndarray) -> None:
        """A frame with no view (the replay's gap card): the same card, no row in the CSV."""
        if self._video is not None:
            self._video.write(shown)

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if self._video is None:
            return
        self._video.close()
        if exc_type is not None:
            self.video_path.unlink(missing_ok=True)
            return
        with self.csv_path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_s", "model", "observed_share", "rests_on_inferred"])
            for t, name, share, flagged in self._rows:
                w.writerow([f"{t:.3f}", name, f"{share:.3f}", int(flagged)])
        flagged_n = sum(r[3] for r in self._rows)
        log.info(
            "wrote %s and %s: %d of %d frames rest on inferred content (observed share < %.2f)",
            self.video_path, self.csv_path, flagged_n, len(self._rows),
            self.case.config.well_observed_share,
        )  # fmt: skip
