"""Whether wand observations can give the rig: each check raises ``SolveError`` naming the camera
and what to do (wave the wand where, check which file), before any solving is spent on them."""

from __future__ import annotations

import numpy as np

from calibration.errors import SolveError
from calibration.observations import WandObservations
from calibration.solve import linear
from calibration.solve.config import SolveConfig


def check_cameras(obs: WandObservations) -> None:
    """Two or more cameras, each with its factory calibration."""
    n_cams = len(obs.camera_serials)
    if n_cams < 2:
        raise SolveError(f"the wand data holds {n_cams} camera(s); a rig solve needs two or more")
    for sn in obs.camera_serials:
        if sn not in obs.stereo:
            raise SolveError(f"camera SN{sn} has no factory calibration; add SN{sn}.conf")


def check_coverage(serials: tuple[int, ...], cam_seen: np.ndarray, cfg: SolveConfig) -> None:
    """Every camera must see the wand, together with another camera, in enough sets."""
    n_cams = len(serials)
    others = np.stack([np.delete(cam_seen, c, axis=1).any(axis=1) for c in range(n_cams)], 1)
    alone = cam_seen.sum(axis=0)
    shared = (cam_seen & others).sum(axis=0)
    blind = [f"SN{sn}" for sn, n in zip(serials, alone, strict=True) if n == 0]
    if blind:
        raise SolveError(
            f"camera {', '.join(blind)} never sees all three wand spheres: check that its lens is "
            "clear and that the wand passes through its view, then record the wand again"
        )
    lonely = [f"SN{sn}" for sn, n in zip(serials, shared, strict=True) if n == 0]
    if lonely:
        raise SolveError(
            f"camera {', '.join(lonely)} never sees the wand at the same time as any other "
            "camera, so it cannot be placed relative to the rig (disconnected view graph): wave "
            "the wand where its view overlaps a neighbour's"
        )
    few = [f"SN{sn} ({n} sets)" for sn, n in zip(serials, shared, strict=True) if n < cfg.min_sets]
    if few:
        raise SolveError(
            f"camera {', '.join(few)} sees the wand together with another camera in too few "
            f"sets (need at least {cfg.min_sets}): wave the wand longer where its view overlaps "
            "the other cameras'"
        )


def choose_reference(serials: tuple[int, ...], pair: np.ndarray, cfg: SolveConfig) -> int:
    """The reference camera's column: the configured one, else the camera that shares the most
    sets with the others (``pair``: sets each two cameras share)."""
    if cfg.reference_serial is None:
        return int(np.argmax(pair.sum(axis=1)))
    if cfg.reference_serial not in serials:
        known = ", ".join(f"SN{s}" for s in serials)
        raise SolveError(
            f"reference camera SN{cfg.reference_serial} is not in the wand data; use one of {known}"
        )
    return serials.index(cfg.reference_serial)


def check_wand(
    serials: tuple[int, ...],
    stereo: list[linear.StereoWand],
    expected_mm: tuple[float, float, float],
    cfg: SolveConfig,
) -> None:
    """Each ZED X measures the wand in metres on its own: it must agree with the spec, to within
    ``wand_tolerance`` plus three standard errors of its median (far cameras measure noisily)."""
    exp = np.asarray(expected_mm)
    measured, bad = {}, {}
    for sn, s in zip(serials, stereo, strict=True):
        d = s.distances_mm()
        if len(d) < cfg.min_pair_sets:
            continue
        m = np.median(d, axis=0)
        se = 1.4826 * 1.2533 * np.median(np.abs(d - m), axis=0) / np.sqrt(len(d))
        measured[sn] = m
        if (np.abs(m - exp) > cfg.wand_tolerance * exp + 3 * se).any():
            bad[sn] = m
    if not bad:
        return

    def mm(v: np.ndarray) -> str:
        return "/".join(f"{x:.0f}" for x in v) + " mm"

    said = "; ".join(f"SN{sn} measures {mm(m)}" for sn, m in bad.items())
    if 2 * len(bad) > len(measured):
        raise SolveError(
            f"the wand does not match its description: {said} (first-middle/middle-last/"
            f"first-last) where the wand spec says {mm(exp)}; check wand.toml against the wand "
            "that was waved, and that the spheres are labelled in the right order"
        )
    raise SolveError(
        f"camera {said} (first-middle/middle-last/first-last) where the wand spec and the other "
        f"cameras say {mm(exp)}: check that this camera's SN<serial>.conf factory file in the "
        "session belongs to it and matches the recorded resolution"
    )
