"""The linear start of the rig solve: each ZED X triangulates the wand on its own (checked against
the wand's spec), then the cameras' poses relative to the reference follow along the maximum
spanning tree of shared sets (``calibration.solve.linear`` holds the maths)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from calibration.errors import SolveError
from calibration.observations import WandObservations
from calibration.solve import bundle, linear
from calibration.solve.checks import check_wand
from calibration.solve.config import SolveConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LinearStart:
    """What the later stages reuse from the start: the sensor models, the observations in
    normalised coordinates ``xn`` (as ``linear.normalised``), each camera's own stereo view of the
    wand, and the starting poses ``R`` (C, 3, 3), ``t`` (C, 3) with how each camera got its pose."""

    sensors: bundle.SensorModels
    xn: np.ndarray
    stereo: list[linear.StereoWand]
    R: np.ndarray
    t: np.ndarray
    how: dict[int, str]  # camera serial -> how it was initialised


def linear_start(
    obs: WandObservations, seen: np.ndarray, pair: np.ndarray, ref: int, cfg: SolveConfig
) -> LinearStart:
    """``seen`` (N, S): sensor s saw the wand in set k; ``pair`` (C, C): sets two cameras share;
    ``ref``: the reference camera's column. Raises ``SolveError`` on a wand that does not match
    its spec or cameras that cannot be linked."""
    serials = obs.camera_serials
    sensors = bundle.SensorModels.from_observations(obs)
    xn = linear.normalised(obs)
    stereo = [
        linear.stereo_wand(xn, seen, sensors, c, cfg.stereo_max_error_px)
        for c in range(len(serials))
    ]
    check_wand(serials, stereo, obs.wand.distances_mm, cfg)
    expected_m = np.asarray(obs.wand.distances_mm) / 1000.0
    R, t, how = _chain_poses(serials, ref, pair, seen, xn, stereo, sensors, expected_m, cfg)
    return LinearStart(sensors=sensors, xn=xn, stereo=stereo, R=R, t=t, how=how)


def _chain_poses(
    serials: tuple[int, ...],
    ref: int,
    pair: np.ndarray,
    seen: np.ndarray,
    xn: np.ndarray,
    stereo: list[linear.StereoWand],
    sensors: bundle.SensorModels,
    expected_m: np.ndarray,
    cfg: SolveConfig,
) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """Poses relative to the reference along the maximum spanning tree of shared sets."""
    names = [f"SN{sn}" for sn in serials]
    parent = linear.maximum_spanning_tree(np.where(pair >= cfg.min_pair_sets, pair, 0), ref)
    if (parent == -2).any():
        lost = ", ".join(names[c] for c in np.flatnonzero(parent == -2))
        raise SolveError(
            f"camera {lost} shares fewer than {cfg.min_pair_sets} wand sets with any camera "
            f"linked to the reference {names[ref]} (disconnected view graph): wave the wand "
            "through the views these cameras share with the others"
        )
    try:
        R, t, how = linear.chain_poses(
            parent,
            seen,
            xn,
            stereo,
            sensors,
            expected_m,
            names,
            min_sets=cfg.min_pair_sets,
            ransac_threshold_m=cfg.ransac_threshold_m,
            ransac_iterations=cfg.ransac_iterations,
            rng=np.random.default_rng(cfg.seed),
        )
    except linear.LinkError as exc:
        pair_names = f"{names[exc.child]} and {names[exc.parent]}"
        if exc.reason == "few":
            raise SolveError(
                f"cameras {pair_names} share too few sets where single sensors see the whole "
                "wand to be placed relative to each other: wave the wand through the views they "
                "share"
            ) from None
        raise SolveError(
            f"cameras {pair_names}: the wand positions they share are degenerate (the wand "
            "stayed in one place or moved along one line), so no relative pose follows from "
            "them: wave the wand through the whole volume both cameras see"
        ) from None
    for c, text in how.items():
        log.info("linear start: %s by %s", names[c], text)
    return R, t, {serials[c]: text for c, text in how.items()}
