"""The report's pictures made from the case: each role's view at the chosen times beside the
real camera nearest that role's eye, each contact's real camera still, and the observed share
of each role's view over the case (``reconstructor/replay/observed.py`` has the measure).

A sealed session read without its identity gives no real frames: the caller passes
``real=None`` and the page says why the real panels are empty.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reconstructor.data.views import EYE_NEAR_M
from reconstructor.errors import ObservedError
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.observed_case import CaseObserved
from reconstructor.replay.path import CameraPath
from reconstructor.replay.run import RealCameras, case_raster, render_view

log = logging.getLogger(__name__)
THUMB_PX = (320, 200)  # a role's view in the report (the page shows it 320 px wide)
SHARE_PX = (160, 100)  # the observed share is a mean over the frame: a small one suffices
MAX_SHARE_TIMESTAMPS = 60  # evenly spread over a longer case (the report says so)


@dataclass(frozen=True)
class Thumb:
    role: str
    t_s: float
    model: str  # the case timestamp shown (the last at or before t_s)
    view_rgb: np.ndarray
    observed_share: float  # of this view; NaN when unknown
    real_rgb: np.ndarray | None  # None: no frame (sealed, gone, or missing from the set)
    real_label: str = ""


@dataclass(frozen=True)
class RoleShare:
    role: str
    instants: int  # case timestamps inside the role's keyframes (not its gaps) measured
    mean_share: float  # mean observed share of the role's view over them; NaN: unknown
    inferred_instants: int  # of them, under well_observed_share: the view rests on inference
    note: str = ""  # why unknown


def _inside(path: CameraPath, t_s: float) -> bool:
    """Inside the role's keyframes and outside its gaps (no one knows where the eye was there:
    the report shows no view from the spline through a gap)."""
    a, b = path.span_s
    return a - 1e-9 <= t_s <= b + 1e-9 and path.gap_at(t_s) is None


def role_thumbs(
    models: CaseModels, paths: list[CameraPath], times_s: list[float],
    real: RealCameras | None, observed: CaseObserved,
) -> list[Thumb]:  # fmt: skip
    """Each role at each time inside both the case and its keyframes, outside its gaps."""
    raster = case_raster(models.folder, EYE_NEAR_M)
    order = [models.entry_at(t) for t in times_s]
    out = []
    with ModelSource(models, order) as source:
        for t, entry in zip(times_s, order, strict=True):
            g = source.get(entry)
            for path in (p for p in paths if _inside(p, t)):
                cam = path.camera(t, THUMB_PX)
                rgb, _, _ = render_view(g, cam, raster)
                share = _share(observed, entry, g, path.camera(t, SHARE_PX), raster)
                frame = real.frame(cam.pose.centre_m, t) if real is not None else None
                out.append(Thumb(
                    role=path.name, t_s=t, model=entry.name, view_rgb=rgb, observed_share=share,
                    real_rgb=frame[0] if frame else None, real_label=frame[1] if frame else "",
                ))  # fmt: skip
    return out


def _share(observed: CaseObserved, entry, g, camera, raster) -> float:
    try:
        return observed.render(entry, g, camera, raster).share
    except ObservedError as exc:
        log.debug("%s: observed share unknown: %s", entry.name, exc)
        return float("nan")


def role_shares(
    models: CaseModels, paths: list[CameraPath], observed: CaseObserved
) -> tuple[list[RoleShare], int]:
    """Per role, its view's observed share over the case's timestamps (at most
    ``MAX_SHARE_TIMESTAMPS``, evenly spread); and how many timestamps were measured."""
    entries = list(models.entries)
    if len(entries) > MAX_SHARE_TIMESTAMPS:
        pick = np.linspace(0, len(entries) - 1, MAX_SHARE_TIMESTAMPS).round().astype(int)
        entries = [entries[k] for k in dict.fromkeys(pick.tolist())]
    raster = case_raster(models.folder, EYE_NEAR_M)
    shares: dict[str, list[float]] = {p.name: [] for p in paths}
    note = ""
    with ModelSource(models, entries) as source:
        for entry in entries:
            g = source.get(entry)
            for path in (p for p in paths if _inside(p, entry.t_s)):
                cam = path.camera(entry.t_s, SHARE_PX)
                try:
                    shares[path.name].append(observed.render(entry, g, cam, raster).share)
                except ObservedError as exc:
                    note = str(exc)
                    shares[path.name].append(float("nan"))
    well = observed.config.well_observed_share
    rows = []
    for name, values in shares.items():
        v = np.array(values)
        known = v[np.isfinite(v)]
        rows.append(RoleShare(
            role=name, instants=len(v), mean_share=float(known.mean()) if len(known) else np.nan,
            inferred_instants=int((known < well).sum()),
            note="" if len(known) else (note or "no case timestamp inside its keyframes"),
        ))  # fmt: skip
    return rows, len(entries)


def event_still(real: RealCameras, contact_m: tuple[float, float, float], t_s: float):
    """(RGB, label) of the real camera nearest an event's contact point at its peak, or None."""
    return real.frame(np.asarray(contact_m, dtype=np.float64), t_s)


def open_real(models: CaseModels, identity, clock) -> RealCameras | None:
    """The session's real frames (labelled with ``clock``'s time of day), or None when the
    session or calibration is gone."""
    session = Path(models.index.session)
    if not session.is_file() or not (models.folder / "calibration.toml").is_file():
        return None
    return RealCameras(models, identity, clock)
