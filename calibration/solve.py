"""Solve the rig's extrinsics from wand observations: ``solve(obs) -> Solution``.

Example::

    from calibration.solve import SolveConfig, solve
    solution = solve(observations, SolveConfig(max_sets=800))
    solution.calibration.write("calibration.toml")

Steps:

1. checks: every camera sees the wand together with another camera in enough sets, and the
   cameras' own stereo measures the wand the spec describes (else ``SolveError``, naming the
   camera and what to do);
2. linear start (``calibration.linear``): each ZED X triangulates the spheres in metres on its
   own; poses relative to the reference camera by RANSAC-Kabsch along a maximum spanning tree of
   the co-visibility graph; an essential matrix plus the wand's length where a camera has no
   stereo pair;
3. sparse robust bundle adjustment (``calibration.bundle``): 6 numbers per ZED X (its right sensor
   follows through the factory transform), 5 per set (a rigid wand), ``least_squares`` with a
   robust loss and an analytic sparse Jacobian, over at most ``max_sets`` sets (``thin_sets``:
   evenly in time, with a share kept for every camera); outlier rejection with a cut-off
   shrinking from 15 to 1 px (never below 5 robust SDs of a sensor's residuals), re-solving
   after each round;
4. every set, with the cameras fixed: the wand trajectory, per-observation residuals, and the
   wand length from unconstrained triangulation (the wand score);
5. world frame (``calibration.world_frame``): the floor at z = 0 if the wand lay on it, else the
   reference camera's left sensor.

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

from calibration import bundle, linear
from calibration.observations import SensorKey, WandObservations
from calibration.world_frame import find_floor
from protocol.camera import Pose
from protocol.errors import ConfigError, UserError
from protocol.formats.rig_calibration import RigCalibration, SensorCalibration

log = logging.getLogger(__name__)

LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


class SolveError(UserError, ValueError):
    """Wand data the rig cannot be solved from; the message names the camera and what to do."""


@dataclass(frozen=True, kw_only=True)
class SolveConfig:
    """How to solve. The wand is rigid in the bundle adjustment (see ``calibration.bundle``), so
    there is no weight between wand length and pixels: the spec's distances hold exactly."""

    loss: str = "soft_l1"
    loss_scale_px: float = 1.0
    cutoffs_px: tuple[float, ...] = (15.0, 5.0, 2.0, 1.0)
    cutoff_sigmas: float = 5.0  # never cut below this many robust SDs of the residuals
    max_sets: int = 1000  # bundle-adjust at most this many sets (see ``thin_sets``)
    max_nfev: int = 50  # solver evaluations per round
    reference_serial: int | None = None  # None: the camera that shares the most sets
    min_sets: int = 20  # sets a camera must share with some other camera
    min_pair_sets: int = 10  # sets two cameras must share to be linked in the linear start
    wand_tolerance: float = 0.05  # stereo-measured wand distances vs the spec, relative
    stereo_max_error_px: float = 2.0  # a camera's own triangulation must fit this well
    ransac_threshold_m: float = 0.03  # Kabsch inlier distance at 2 m (grows with depth²)
    ransac_iterations: int = 200
    seed: int = 0
    floor: bool = True  # look for the wand lying on the floor
    floor_min_still_s: float = 0.5
    floor_still_tolerance_px: float = 1.5  # "still": the wand's image moves less than this
    floor_max_height_m: float = 0.1
    floor_max_tilt_deg: float = 10.0
    pass_reprojection_px: float = 0.3  # verdict "pass" at or below this mean, and ...
    pass_wand_score: float = 0.5  # ... at or below this wand score, and ...
    pass_scale_tolerance: float = 0.005  # ... every camera's baseline agreeing with the wand

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ConfigError(f"SolveConfig.loss={self.loss!r}; choose one of {', '.join(LOSSES)}")
        positive = (
            *("loss_scale_px", "cutoff_sigmas", "wand_tolerance", "stereo_max_error_px"),
            *("ransac_threshold_m", "floor_still_tolerance_px", "floor_max_height_m"),
            *("floor_min_still_s", "floor_max_tilt_deg", "pass_reprojection_px"),
            *("pass_wand_score", "pass_scale_tolerance"),
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"SolveConfig.{name}={getattr(self, name)!r} must be > 0")
        cut = tuple(float(c) for c in self.cutoffs_px)
        if not cut or any(c <= 0 for c in cut) or list(cut) != sorted(cut, reverse=True):
            raise ConfigError(
                f"SolveConfig.cutoffs_px={self.cutoffs_px!r} must be positive and shrinking"
            )
        object.__setattr__(self, "cutoffs_px", cut)
        for name, low in (("max_sets", 20), ("max_nfev", 5), ("min_sets", 3)):
            if getattr(self, name) < low:
                raise ConfigError(f"SolveConfig.{name}={getattr(self, name)!r} must be >= {low}")
        if not 3 <= self.min_pair_sets <= self.min_sets:
            raise ConfigError(f"SolveConfig.min_pair_sets={self.min_pair_sets} must be 3..min_sets")


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


def solve(obs: WandObservations, config: SolveConfig | None = None) -> Solution:
    """The rig's poses from wand observations; raises ``SolveError`` on unusable data."""
    cfg = config or SolveConfig()
    started = time.perf_counter()
    serials = obs.camera_serials
    n_cams, n_sets = len(serials), len(obs.set_unix_ns)
    if n_cams < 2:
        raise SolveError(f"the wand data holds {n_cams} camera(s); a rig solve needs two or more")
    for sn in serials:
        if sn not in obs.stereo:
            raise SolveError(f"camera SN{sn} has no factory calibration; add SN{sn}.conf")
    seen = np.asarray(obs.seen())
    cam_seen = np.asarray(seen.reshape(n_sets, n_cams, 2).any(axis=2))
    pair = (cam_seen[:, :, None] & cam_seen[:, None, :]).sum(axis=0)
    pair *= 1 - np.eye(n_cams, dtype=pair.dtype)
    _check_coverage(serials, cam_seen, cfg)
    ref = _reference(serials, pair, cfg)

    # linear start
    sensors = bundle.SensorModels.from_observations(obs)
    xn = linear.normalised(obs)
    stereo = [
        linear.stereo_wand(xn, seen, sensors, c, cfg.stereo_max_error_px) for c in range(n_cams)
    ]
    _check_wand(serials, stereo, obs.wand.distances_mm, cfg)
    expected_m = np.asarray(obs.wand.distances_mm) / 1000.0
    R0, t0, start = _linear_start(serials, ref, pair, seen, xn, stereo, sensors, expected_m, cfg)

    # bundle adjustment over sets two or more cameras see
    positions_m = np.asarray(obs.wand.sphere_positions_mm) / 1000.0
    offsets_m = positions_m - positions_m.mean()
    flat = bundle.FlatObservations.from_points(obs.points_px)
    ba_sets = thin_sets(np.flatnonzero(cam_seen.sum(axis=1) >= 2), cam_seen, cfg.max_sets)
    state = bundle.RigState(R0, t0, np.full((n_sets, 3), np.nan), np.full((n_sets, 3), np.nan))
    linear.init_wands(state, ba_sets, xn, sensors, offsets_m)
    in_ba = np.isin(flat.set_index, ba_sets) & np.isfinite(state.p[flat.set_index, 0])
    log.info(
        "bundle adjustment over %d of %d sets, %d observations", len(ba_sets), n_sets, in_ba.sum()
    )
    free = tuple(c for c in range(n_cams) if c != ref)
    state, _, rounds = _adjust(state, flat.subset(in_ba), sensors, offsets_m, free, cfg)

    # every set, with the cameras fixed: trajectory, residuals, inliers
    state.p[:], state.d[:] = np.nan, np.nan
    linear.init_wands(state, np.flatnonzero(seen.sum(axis=1) >= 2), xn, sensors, offsets_m)
    fit = np.isfinite(state.p[flat.set_index, 0])
    state, use, _ = _adjust(state, flat.subset(fit), sensors, offsets_m, (), cfg)
    inlier = np.zeros(len(flat), bool)
    inlier[np.flatnonzero(fit)[use]] = True
    supported = bundle.supported_sets(flat, inlier, n_sets)
    state.p[~supported], state.d[~supported] = np.nan, np.nan
    inlier &= supported[flat.set_index]
    res = bundle.residuals(state, flat, sensors, offsets_m)
    errors = np.linalg.norm(res[inlier], axis=1)
    if not len(errors) or np.median(errors) > 5.0:
        median = float(np.median(errors)) if len(errors) else float("nan")
        raise SolveError(
            f"the bundle adjustment did not converge (median reprojection error {median:.1f} "
            "px): the wand data is degenerate or mislabelled; check the detections and record "
            "the wand again"
        )

    # world frame
    centres = state.centres(offsets_m)
    floor = None
    if cfg.floor:
        floor = find_floor(
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
    Rw, tw = (floor.R, floor.t) if floor is not None else (np.eye(3), np.zeros(3))
    frame = "floor" if floor is not None else f"camera:SN{serials[ref]}-left"

    quality = bundle.residual_stats(errors)
    lengths = linear.free_lengths_mm(state, flat, inlier, xn, sensors)
    nan = float("nan")
    quality |= {
        "observations_used": int(inlier.sum()),
        "observations_rejected": int((~inlier).sum()),
        "wand_length_mm_mean": float(np.mean(lengths)) if len(lengths) else nan,
        "wand_length_mm_sd": float(np.std(lengths)) if len(lengths) else nan,
        "wand_length_mm_spec": obs.wand.distances_mm[2],
        "wand_score": float(100 * np.std(lengths) / np.mean(lengths)) if len(lengths) else nan,
        "wand_sets": len(lengths),
    }
    ratios = {
        sn: stereo[c].depth_ratio(centres, state.R[c], state.t[c]) for c, sn in enumerate(serials)
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
        "initialisation": "; ".join(f"SN{sn}: {start[sn]}" for sn in serials),
        "sets_total": n_sets,
        "sets_bundle": len(ba_sets),
        "sets_fitted": int(supported.sum()),
        "bundle_rounds": len(rounds),
        "cutoff_px_final": rounds[-1].cutoff_px if rounds else nan,
        "solve_seconds": time.perf_counter() - started,
    }
    quality["verdict"] = _verdict(quality, finite, cfg)

    sensor_cals = []
    for c, sn in enumerate(serials):
        R = state.R[c] @ Rw.T
        left = Pose(R=R, t_m=state.t[c] - R @ tw)
        right = obs.stereo[sn].right_from_left.compose(left)
        for side, pose in (("left", left), ("right", right)):
            key = SensorKey(sn, side)
            s = 2 * c + (side == "right")
            stats = bundle.sensor_stats(flat, inlier, res, s)
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
    calibration = RigCalibration(
        sensors=tuple(sensor_cals),
        resolution=obs.stereo[serials[0]].resolution,
        world_frame=frame,
        quality=quality,
        metadata={"solver": "wand bundle adjustment (calibration.solve)"},
    )
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
            obs.sensors, flat.set_index, flat.sensor, flat.sphere, flat.px, res, inlier
        ),
        trajectory_m=centres @ Rw.T + tw,
        wand_lengths_mm=np.asarray(lengths, dtype=np.float64),
        floor_sets=np.zeros(0, int) if floor is None else floor.floor_sets,
        bundle_sets=ba_sets,
        reference_serial=serials[ref],
        start=start,
        rounds=tuple(rounds),
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


# ---- checks --------------------------------------------------------------------------------


def _check_coverage(serials: tuple[int, ...], cam_seen: np.ndarray, cfg: SolveConfig) -> None:
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


def _reference(serials: tuple[int, ...], pair: np.ndarray, cfg: SolveConfig) -> int:
    if cfg.reference_serial is None:
        return int(np.argmax(pair.sum(axis=1)))
    if cfg.reference_serial not in serials:
        known = ", ".join(f"SN{s}" for s in serials)
        raise SolveError(
            f"reference camera SN{cfg.reference_serial} is not in the wand data; use one of {known}"
        )
    return serials.index(cfg.reference_serial)


def _check_wand(
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


def _linear_start(
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
