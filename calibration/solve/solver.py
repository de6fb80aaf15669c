"""Solve the rig's extrinsics from wand observations: ``solve(obs) -> Solution``.

Example::

    from calibration.solve.config import SolveConfig
    from calibration.solve.solver import solve
    solution = solve(observations, SolveConfig(max_sets=800))
    solution.calibration.write("calibration.toml")

Steps:

1. checks (``calibration.solve.checks``): every camera sees the wand together with another
   camera in enough sets, and the cameras' own stereo measures the wand the spec describes (else
   ``SolveError``, naming the camera and what to do);
2. linear start (``calibration.solve.start``, the maths in ``calibration.solve.linear``): each
   ZED X triangulates the spheres in metres on its own; poses relative to the reference camera by
   RANSAC-Kabsch along a maximum spanning tree of the co-visibility graph; an essential matrix
   plus the wand's length where a camera has no stereo pair;
3. sparse robust bundle adjustment (``calibration.solve.bundle``): 6 numbers per ZED X (its right
   sensor follows through the factory transform), 5 per set (a rigid wand), ``least_squares``
   with a robust loss and an analytic sparse Jacobian, over at most ``max_sets`` sets
   (``thin_sets``: evenly in time, with a share kept for every camera); outlier rejection with a
   cut-off shrinking from 15 to 1 px (never below 5 robust SDs of a sensor's residuals),
   re-solving after each round;
4. every set, with the cameras fixed: the wand trajectory, per-observation residuals, and the
   wand length from unconstrained triangulation (the wand score);
5. world frame (``calibration.solve.world_frame``): the floor at z = 0 if the wand lay on it, else
   the reference camera's left sensor.

Speed: a 2-minute session at 30 fps (3600 sets x 8 sensors) solves in about 6-10 s on 2 cores,
with the bundle adjustment over 1000 of the sets; the fixed-camera pass over all of them is
cheap (5 unknowns per set, independent of each other).

Scale comes from the wand; each camera's factory baseline is cross-checked against it
(``scale_check_ratio``: the median ratio of sphere depths from a camera's own stereo to those of
the solution; 1.0 means the baselines and the wand agree on scale).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from calibration.errors import SolveError
from calibration.observations import SensorKey, WandObservations
from calibration.solve import bundle, linear
from calibration.solve.checks import check_cameras, check_coverage, choose_reference
from calibration.solve.config import SolveConfig
from calibration.solve.start import LinearStart, linear_start
from calibration.solve.world_frame import FloorFrame, find_floor
from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration, SensorCalibration

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ObservationResiduals:
    """One row per observed sphere centre, for the report. ``residual_px`` is projected minus
    observed (NaN where the set could not be fitted); ``inlier`` marks rows the solution used."""

    sensors: tuple[SensorKey, ...]
    set_index: np.ndarray  # (M,) int
    sensor_index: np.ndarray  # (M,) int, into ``sensors``
    sphere_index: np.ndarray  # (M,) int
    pixel_px: np.ndarray  # (M, 2) observed, distorted pixels
    residual_px: np.ndarray  # (M, 2)
    inlier: np.ndarray  # (M,) bool

    @property
    def error_px(self) -> np.ndarray:
        return np.linalg.norm(self.residual_px, axis=1)


@dataclass(frozen=True)
class Solution:
    calibration: RigCalibration
    residuals: ObservationResiduals
    trajectory_m: np.ndarray  # (N, 3, 3) sphere centres in the world frame, NaN where unknown
    floor_sets: np.ndarray  # (F,) set indices where the wand lay on the floor
    bundle_sets: np.ndarray  # (B,) set indices the bundle adjustment used
    reference_serial: int
    start: dict[int, str] = field(default_factory=dict)  # how each camera was initialised
    rounds: tuple[bundle.Round, ...] = ()
    wand_lengths_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))  # freely triangulated


@dataclass(frozen=True)
class _Views:
    """Who saw the wand when: ``seen`` (N, S) per set and sensor, ``cam_seen`` (N, C) per set and
    camera (either sensor), ``pair`` (C, C) the sets two cameras share (zero diagonal)."""

    seen: np.ndarray
    cam_seen: np.ndarray
    pair: np.ndarray


@dataclass(frozen=True)
class _Fitted:
    """Every set with the cameras fixed: the state, the observations kept (M,), the sets with a
    fitted wand (N,), every observation's residual (M, 2) px and the kept ones' errors px."""

    state: bundle.RigState
    inlier: np.ndarray
    supported: np.ndarray
    residuals_px: np.ndarray
    errors_px: np.ndarray


def solve(obs: WandObservations, config: SolveConfig | None = None) -> Solution:
    """The rig's poses from wand observations; raises ``SolveError`` on unusable data."""
    cfg = config or SolveConfig()
    started = time.perf_counter()
    serials = obs.camera_serials
    check_cameras(obs)
    views = _views(obs)
    check_coverage(serials, views.cam_seen, cfg)
    ref = choose_reference(serials, views.pair, cfg)
    start = linear_start(obs, views.seen, views.pair, ref, cfg)
    positions_m = np.asarray(obs.wand.sphere_positions_mm) / 1000.0
    offsets_m = positions_m - positions_m.mean()
    flat = bundle.FlatObservations.from_points(obs.points_px)
    state, ba_sets, rounds = _adjust_cameras(obs, views, start, flat, offsets_m, ref, cfg)
    fitted = _fit_every_set(state, views, start, flat, offsets_m, cfg)
    centres = fitted.state.centres(offsets_m)
    floor = _find_floor(obs, fitted.state, centres, cfg)
    Rw, tw = (floor.R, floor.t) if floor is not None else (np.eye(3), np.zeros(3))
    frame = "floor" if floor is not None else f"camera:SN{serials[ref]}-left"
    lengths = linear.free_lengths_mm(fitted.state, flat, fitted.inlier, start.xn, start.sensors)
    quality, scale_ratios = _quality(obs, start, fitted, lengths, centres, floor, frame, ref, cfg)
    quality |= {
        "sets_total": len(obs.set_unix_ns),
        "sets_bundle": len(ba_sets),
        "sets_fitted": int(fitted.supported.sum()),
        "bundle_rounds": len(rounds),
        "cutoff_px_final": rounds[-1].cutoff_px if rounds else float("nan"),
        "solve_seconds": time.perf_counter() - started,
    }
    quality["verdict"] = _verdict(quality, scale_ratios, cfg)
    calibration = _rig_calibration(obs, fitted, flat, Rw, tw, frame, quality)
    log.info(
        "solved in %.1f s: reprojection %.3f px mean, wand score %.3f %%, world frame %s",
        quality["solve_seconds"],
        quality["reprojection_px_mean"],
        quality["wand_score"],
        frame,
    )
    return Solution(
        calibration=calibration,
        residuals=ObservationResiduals(
            obs.sensors,
            flat.set_index,
            flat.sensor,
            flat.sphere,
            flat.px,
            fitted.residuals_px,
            fitted.inlier,
        ),
        trajectory_m=centres @ Rw.T + tw,
        wand_lengths_mm=np.asarray(lengths, dtype=np.float64),
        floor_sets=np.zeros(0, int) if floor is None else floor.floor_sets,
        bundle_sets=ba_sets,
        reference_serial=serials[ref],
        start=start.how,
        rounds=tuple(rounds),
    )


def _views(obs: WandObservations) -> _Views:
    n_cams, n_sets = len(obs.camera_serials), len(obs.set_unix_ns)
    seen = np.asarray(obs.seen())
    cam_seen = np.asarray(seen.reshape(n_sets, n_cams, 2).any(axis=2))
    pair = (cam_seen[:, :, None] & cam_seen[:, None, :]).sum(axis=0)
    pair *= 1 - np.eye(n_cams, dtype=pair.dtype)
    return _Views(seen=seen, cam_seen=cam_seen, pair=pair)


def _adjust_cameras(
    obs: WandObservations,
    views: _Views,
    start: LinearStart,
    flat: bundle.FlatObservations,
    offsets_m: np.ndarray,
    ref: int,
    cfg: SolveConfig,
) -> tuple[bundle.RigState, np.ndarray, list[bundle.Round]]:
    """The bundle adjustment of every camera but the reference, over (at most ``max_sets`` of)
    the sets two or more cameras see; the state, the sets used and the rounds."""
    n_cams, n_sets = len(obs.camera_serials), len(obs.set_unix_ns)
    shared = np.flatnonzero(views.cam_seen.sum(axis=1) >= 2)
    ba_sets = thin_sets(shared, views.cam_seen, cfg.max_sets)
    unknown = np.full((n_sets, 3), np.nan)
    state = bundle.RigState(start.R, start.t, unknown, unknown.copy())
    linear.init_wands(state, ba_sets, start.xn, start.sensors, offsets_m)
    in_ba = np.isin(flat.set_index, ba_sets) & np.isfinite(state.p[flat.set_index, 0])
    log.info(
        "bundle adjustment over %d of %d sets, %d observations", len(ba_sets), n_sets, in_ba.sum()
    )
    free = tuple(c for c in range(n_cams) if c != ref)
    state, _, rounds = _adjust(state, flat.subset(in_ba), start.sensors, offsets_m, free, cfg)
    return state, ba_sets, rounds


def _fit_every_set(
    state: bundle.RigState,
    views: _Views,
    start: LinearStart,
    flat: bundle.FlatObservations,
    offsets_m: np.ndarray,
    cfg: SolveConfig,
) -> _Fitted:
    """Every set two or more sensors see, with the cameras fixed: the wand trajectory, the
    residuals and which observations are kept. Raises ``SolveError`` when the solve did not
    converge."""
    n_sets = len(views.seen)
    state.p[:], state.d[:] = np.nan, np.nan
    sets = np.flatnonzero(views.seen.sum(axis=1) >= 2)
    linear.init_wands(state, sets, start.xn, start.sensors, offsets_m)
    fit = np.isfinite(state.p[flat.set_index, 0])
    state, use, _ = _adjust(state, flat.subset(fit), start.sensors, offsets_m, (), cfg)
    inlier = np.zeros(len(flat), bool)
    inlier[np.flatnonzero(fit)[use]] = True
    supported = bundle.supported_sets(flat, inlier, n_sets)
    state.p[~supported], state.d[~supported] = np.nan, np.nan
    inlier &= supported[flat.set_index]
    res = bundle.residuals(state, flat, start.sensors, offsets_m)
    errors = np.linalg.norm(res[inlier], axis=1)
    if not len(errors) or np.median(errors) > 5.0:
        median = float(np.median(errors)) if len(errors) else float("nan")
        raise SolveError(
            f"the bundle adjustment did not converge (median reprojection error {median:.1f} "
            "px): the wand data is degenerate or mislabelled; check the detections and record "
            "the wand again"
        )
    return _Fitted(state, inlier, supported, res, errors)


def _find_floor(
    obs: WandObservations, state: bundle.RigState, centres: np.ndarray, cfg: SolveConfig
) -> FloorFrame | None:
    """The floor, where the wand lay still on it (``cfg.floor``), else None."""
    if not cfg.floor:
        return None
    return find_floor(
        centres,
        obs.points_px,
        (obs.set_unix_ns - obs.set_unix_ns.min()) / 1e9,
        state.R,
        -(state.R.transpose(0, 2, 1) @ state.t[:, :, None])[:, :, 0],
        obs.wand.radius_m,
        min_still_s=cfg.floor_min_still_s,
        tolerance_px=cfg.floor_still_tolerance_px,
        max_height_m=cfg.floor_max_height_m,
        max_tilt_deg=cfg.floor_max_tilt_deg,
    )


def _quality(
    obs: WandObservations,
    start: LinearStart,
    fitted: _Fitted,
    lengths: np.ndarray,
    centres: np.ndarray,
    floor: FloorFrame | None,
    frame: str,
    ref: int,
    cfg: SolveConfig,
) -> tuple[dict[str, object], list[float]]:
    """The calibration's ``[quality]`` (the solve's part; the report adds its own): residuals,
    the freely triangulated wand, each camera's scale cross-check and the world frame; and the
    finite scale ratios, for the verdict."""
    serials, state = obs.camera_serials, fitted.state
    quality: dict[str, object] = dict(bundle.residual_stats(fitted.errors_px))
    nan = float("nan")
    quality |= {
        "observations_used": int(fitted.inlier.sum()),
        "observations_rejected": int((~fitted.inlier).sum()),
        "wand_length_mm_mean": float(np.mean(lengths)) if len(lengths) else nan,
        "wand_length_mm_sd": float(np.std(lengths)) if len(lengths) else nan,
        "wand_length_mm_spec": obs.wand.distances_mm[2],
        "wand_score": float(100 * np.std(lengths) / np.mean(lengths)) if len(lengths) else nan,
        "wand_sets": len(lengths),
    }
    ratios = {
        sn: start.stereo[c].depth_ratio(centres, state.R[c], state.t[c])
        for c, sn in enumerate(serials)
    }
    finite = [r for r in ratios.values() if np.isfinite(r)]
    quality["scale_check_ratio"] = float(np.median(finite)) if finite else nan
    quality |= {f"scale_check_ratio_SN{sn}": r for sn, r in ratios.items()}
    quality |= {
        "world_frame": frame,
        "floor_sets": 0 if floor is None else len(floor.floor_sets),
        "floor_normal_source": "" if floor is None else floor.normal_source,
        "floor_plane_rms_mm": nan if floor is None else floor.plane_rms_mm,
        "reference_camera": f"SN{serials[ref]}",
        "initialisation": "; ".join(f"SN{sn}: {start.how[sn]}" for sn in serials),
    }
    return quality, finite


def _rig_calibration(
    obs: WandObservations,
    fitted: _Fitted,
    flat: bundle.FlatObservations,
    Rw: np.ndarray,
    tw: np.ndarray,
    frame: str,
    quality: dict[str, object],
) -> RigCalibration:
    """Both sensors of every camera in the world frame (``x_world_new = Rw x + tw``), with their
    residual statistics."""
    state = fitted.state
    sensor_cals = []
    for c, sn in enumerate(obs.camera_serials):
        R = state.R[c] @ Rw.T
        left = Pose(R=R, t_m=state.t[c] - R @ tw)
        right = obs.stereo[sn].right_from_left.compose(left)
        for side, pose in (("left", left), ("right", right)):
            key = SensorKey(sn, side)
            s = 2 * c + (side == "right")
            stats = bundle.sensor_stats(flat, fitted.inlier, fitted.residuals_px, s)
            stats["frames_rejected_by_detection"] = float(sum(obs.rejected.get(key, {}).values()))
            sensor_cals.append(
                SensorCalibration(
                    name=key.name,
                    camera_serial=sn,
                    side=side,
                    intrinsics=obs.intrinsics(key),
                    pose=pose,
                    stats=stats,
                )
            )
    return RigCalibration(
        sensors=tuple(sensor_cals),
        resolution=obs.stereo[obs.camera_serials[0]].resolution,
        world_frame=frame,
        quality=quality,
        metadata={"solver": "wand bundle adjustment (calibration.solve)"},
    )


def thin_sets(candidates: np.ndarray, cam_seen: np.ndarray, max_sets: int) -> np.ndarray:
    """At most about ``max_sets`` of the candidate set indices, spread evenly in time; a quarter
    of the budget is shared out among the cameras first, so a camera that sees the wand in few
    sets keeps them all. Consecutive sets at 30 fps are nearly the same wand pose, so an even
    thinning loses little information."""
    if len(candidates) <= max_sets:
        return candidates

    def evenly(a: np.ndarray, k: int) -> np.ndarray:
        if len(a) <= k:
            return a
        return a[np.unique(np.round(np.linspace(0, len(a) - 1, k)).astype(int))]

    quota = max_sets // (4 * cam_seen.shape[1])
    keep = [evenly(candidates[cam_seen[candidates, c]], quota) for c in range(cam_seen.shape[1])]
    reserved = np.unique(np.concatenate(keep))
    rest = np.setdiff1d(candidates, reserved)
    return np.union1d(reserved, evenly(rest, max_sets - len(reserved)))


def _adjust(
    state: bundle.RigState,
    flat: bundle.FlatObservations,
    sensors: bundle.SensorModels,
    offsets_m: np.ndarray,
    free: tuple[int, ...],
    cfg: SolveConfig,
) -> tuple[bundle.RigState, np.ndarray, list[bundle.Round]]:
    return bundle.adjust(
        state,
        flat,
        sensors,
        offsets_m,
        free_cameras=free,
        cutoffs_px=cfg.cutoffs_px,
        cutoff_sigmas=cfg.cutoff_sigmas,
        loss=cfg.loss,
        loss_scale_px=cfg.loss_scale_px,
        max_nfev=cfg.max_nfev,
    )


def _verdict(quality: dict[str, object], scale_ratios: list[float], cfg: SolveConfig) -> str:
    """ "pass" when the residuals, the wand score and every camera's scale cross-check are
    within the config's limits, else "check"."""
    ok = float(quality["reprojection_px_mean"]) <= cfg.pass_reprojection_px  # type: ignore[arg-type]
    ok &= float(quality["wand_score"]) <= cfg.pass_wand_score  # type: ignore[arg-type]
    ok &= all(abs(r - 1.0) <= cfg.pass_scale_tolerance for r in scale_ratios)
    return "pass" if ok else "check"
