"""Sparse bundle adjustment of the rig: one pose per ZED X, one rigid wand per set.

Unknowns:

- per camera (except the reference, which fixes the gauge): a rotation increment ``w`` (3, so
  ``R = exp([w]x) @ R0``) and the translation ``t`` (3) of its world-to-left-sensor pose. The
  right sensor follows through the factory transform, ``x_right = R_f @ x_left + T_f``;
- per set: the wand's centroid ``p`` (3) and a tangent increment ``(a, b)`` (2) of its unit
  direction, ``d = normalise(d0 + a e1 + b e2)``. The spheres sit at ``p + o_j d`` with the spec's
  offsets ``o_j`` from the centroid, so the three are collinear with exactly the spec's spacing:
  the inter-sphere distances are hard constraints. That costs 5 numbers per set instead of 9, needs
  no weight between pixels and millimetres, and makes the wand fix the scale; the wand's free
  length is still measured afterwards, by unconstrained triangulation (the wand score).
  The centroid, not the first sphere, is the anchor: position and direction then decouple.

Increments are re-based at every call, so no angle wraps or hits a pole. Residuals are pixel
errors through the full OpenCV distortion model of each sensor. The Jacobian is analytic and
sparse (each residual row touches 6 camera and 5 set columns): finite differences over the same
structure (``jac_sparsity``) would cost about 25 residual evaluations per Jacobian, and
``tests/calibration/test_solve.py`` checks the analytic one against them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.observations import WandObservations
from protocol.camera import Intrinsics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorModels:
    """Per sensor (S = 2 x cameras, left then right of each camera): intrinsics and the
    sensor-from-left transform of its camera."""

    intrinsics: tuple[Intrinsics, ...]
    A: np.ndarray  # (S, 3, 3)
    b: np.ndarray  # (S, 3)

    @classmethod
    def from_observations(cls, obs: WandObservations) -> SensorModels:
        """The factory intrinsics and stereo transforms, in ``obs.sensors`` order."""
        intr, A, b = [], [], []
        for key in obs.sensors:
            st = obs.stereo[key.camera_serial]
            intr.append(obs.intrinsics(key))
            right = key.side == "right"
            A.append(st.R_right_from_left if right else np.eye(3))
            b.append(st.T_right_from_left_m if right else np.zeros(3))
        return cls(tuple(intr), np.asarray(A, float), np.asarray(b, float))

    @property
    def table(self) -> np.ndarray:
        """(S, 12): fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 (a five-term lens has k4 = k5 = k6 = 0)."""
        return np.array([[i.fx_px, i.fy_px, i.cx_px, i.cy_px, *i.dist8] for i in self.intrinsics])


@dataclass(frozen=True)
class FlatObservations:
    """Every finite observation as a row: set, sensor (camera = sensor // 2), sphere, pixel."""

    set_index: np.ndarray  # (M,) int
    sensor: np.ndarray  # (M,) int
    sphere: np.ndarray  # (M,) int
    px: np.ndarray  # (M, 2)

    @classmethod
    def from_points(cls, points_px: np.ndarray) -> FlatObservations:
        """From (N, S, 3, 2) pixels, NaN where not seen."""
        k, s, j = np.nonzero(np.isfinite(points_px).all(axis=3))
        return cls(k, s, j, points_px[k, s, j])

    def __len__(self) -> int:
        return len(self.set_index)

    def subset(self, mask: np.ndarray) -> FlatObservations:
        return FlatObservations(
            self.set_index[mask], self.sensor[mask], self.sphere[mask], self.px[mask]
        )


@dataclass
class RigState:
    """World-to-left-sensor poses (C cameras) and one rigid wand per set (NaN if unknown)."""

    R: np.ndarray  # (C, 3, 3)
    t: np.ndarray  # (C, 3)
    p: np.ndarray  # (N, 3) wand centroids
    d: np.ndarray  # (N, 3) unit directions, first to last sphere

    def copy(self) -> RigState:
        return RigState(self.R.copy(), self.t.copy(), self.p.copy(), self.d.copy())

    def centres(self, offsets_m: np.ndarray) -> np.ndarray:
        """(N, 3, 3) sphere centres."""
        return self.p[:, None, :] + offsets_m[None, :, None] * self.d[:, None, :]


def project(
    Xs: np.ndarray, table: np.ndarray, *, with_jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """(M, 3) sensor-frame points and (M, 12) per-point intrinsics -> (M, 2) distorted pixels and
    (M, 2, 3) d(pixel)/d(point). Matches ``cv2.projectPoints`` with OpenCV's rational model
    (k4 = k5 = k6 = 0 is the five-term one: the denominator is exactly 1)."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = table.T
    z = Xs[:, 2]
    iz = 1.0 / z
    x, y = Xs[:, 0] * iz, Xs[:, 1] * iz
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    px = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    if not with_jacobian:
        return px, None
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    dr = 2 * (dnum - radial * dden) / den  # d radial / d r2, times 2 (quotient rule)
    dxd_dx = radial + x * x * dr + 2 * p1 * y + 6 * p2 * x
    dxd_dy = x * y * dr + 2 * p1 * x + 2 * p2 * y
    dyd_dx = x * y * dr + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + y * y * dr + 6 * p1 * y + 2 * p2 * x
    J = np.empty((len(z), 2, 3))
    # chain: (x, y) = (X/Z, Y/Z)
    J[:, 0, 0] = fx * dxd_dx * iz
    J[:, 0, 1] = fx * dxd_dy * iz
    J[:, 0, 2] = -fx * (dxd_dx * x + dxd_dy * y) * iz
    J[:, 1, 0] = fy * dyd_dx * iz
    J[:, 1, 1] = fy * dyd_dy * iz
    J[:, 1, 2] = -fy * (dyd_dx * x + dyd_dy * y) * iz
    return px, J


def residuals(
    state: RigState, obs: FlatObservations, sensors: SensorModels, offsets_m: np.ndarray
) -> np.ndarray:
    """(M, 2) reprojection residuals (projected - observed) in pixels; NaN for unknown sets."""
    X = state.p[obs.set_index] + offsets_m[obs.sphere, None] * state.d[obs.set_index]
    c = obs.sensor // 2
    Xl = (state.R[c] @ X[:, :, None])[:, :, 0] + state.t[c]
    Xs = (sensors.A[obs.sensor] @ Xl[:, :, None])[:, :, 0] + sensors.b[obs.sensor]
    px, _ = project(Xs, sensors.table[obs.sensor], with_jacobian=False)
    return px - obs.px


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """(C, 3) rotation vectors -> (C, 3, 3) left Jacobians of SO(3)."""
    th = np.linalg.norm(w, axis=1)[:, None, None]
    K = _skew(w)
    small = th < 1e-8
    th = np.where(small, 1.0, th)
    a = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0, (th - np.sin(th)) / th**3)
    return np.eye(3) + a * K + b * (K @ K)


def _tangents(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each (K, 3) unit direction and to each other."""
    helper = np.zeros_like(d)
    helper[np.arange(len(d)), np.argmin(np.abs(d), axis=1)] = 1.0
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(d, e1)


@dataclass
class BundleProblem:
    """The least-squares problem over free cameras and the given sets, for a fixed set of
    observations. Observations of free cameras come first so the sparse rows need no sorting."""

    state: RigState
    obs: FlatObservations
    sensors: SensorModels
    offsets_m: np.ndarray
    sets: np.ndarray  # (K,) set indices solved for
    free_cameras: tuple[int, ...]
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        n_cams = len(self.state.R)
        free = np.full(n_cams, -1)
        free[list(self.free_cameras)] = np.arange(len(self.free_cameras))
        local = np.full(len(self.state.p), -1)
        local[self.sets] = np.arange(len(self.sets))
        k = local[self.obs.set_index]
        if (k < 0).any():
            raise ValueError("observations of sets that are not solved for")
        fc = free[self.obs.sensor // 2]
        order = np.argsort(fc < 0, kind="stable")
        o = self.obs
        self.obs = FlatObservations(
            o.set_index[order], o.sensor[order], o.sphere[order], o.px[order]
        )
        self._k, self._fc = k[order], fc[order]
        self._cam = self.obs.sensor // 2
        self._n_free_obs = int((self._fc >= 0).sum())
        self._table = self.sensors.table[self.obs.sensor]
        self._A = self.sensors.A[self.obs.sensor]
        self._b = self.sensors.b[self.obs.sensor]
        self._R0 = self.state.R.copy()
        self._d0 = self.state.d[self.sets].copy()
        self._e1, self._e2 = _tangents(self._d0)
        nc = 6 * len(self.free_cameras)
        self.n_params = nc + 5 * len(self.sets)
        # sparse structure: free-camera rows hold 6 camera + 5 set entries, the others 5
        set_cols = nc + 5 * self._k[:, None] + np.arange(5)
        cam_cols = 6 * self._fc[:, None] + np.arange(6)
        nf = self._n_free_obs
        idx_free = np.concatenate([cam_cols[:nf], set_cols[:nf]], axis=1)
        idx_free = np.repeat(idx_free[:, None, :], 2, axis=1).ravel()
        idx_fixed = np.repeat(set_cols[nf:, None, :], 2, axis=1).ravel()
        self._indices = np.concatenate([idx_free, idx_fixed])
        counts = np.repeat(np.where(self._fc >= 0, 11, 5), 2)
        self._indptr = np.concatenate([[0], np.cumsum(counts)])

    def x0(self) -> np.ndarray:
        cams = np.concatenate(
            [np.r_[np.zeros(3), self.state.t[c]] for c in self.free_cameras] or [np.zeros(0)]
        )
        sets = np.c_[self.state.p[self.sets], np.zeros((len(self.sets), 2))].ravel()
        return np.concatenate([cams, sets])

    def _unpack(self, x: np.ndarray) -> tuple:
        nc = 6 * len(self.free_cameras)
        cam = x[:nc].reshape(-1, 6)
        R, t = self._R0.copy(), self.state.t.copy()
        w = cam[:, :3]
        if len(self.free_cameras):
            R[list(self.free_cameras)] = (
                Rotation.from_rotvec(w).as_matrix() @ self._R0[list(self.free_cameras)]
            )
            t[list(self.free_cameras)] = cam[:, 3:]
        s = x[nc:].reshape(-1, 5)
        v = self._d0 + s[:, 3:4] * self._e1 + s[:, 4:5] * self._e2
        vn = np.linalg.norm(v, axis=1, keepdims=True)
        return R, t, w, s[:, :3], v / vn, vn

    def apply(self, x: np.ndarray) -> RigState:
        """The state at parameters ``x`` (sets not solved for keep their values)."""
        R, t, _, p, d, _ = self._unpack(x)
        out = self.state.copy()
        out.R, out.t = R, t
        out.p[self.sets], out.d[self.sets] = p, d
        return out

    def _evaluate(self, x: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        key = x.tobytes()
        if self._cache.get("key") == key:
            return self._cache["r"], self._cache["J"]
        R, t, w, p, d, vn = self._unpack(x)
        k, c, j = self._k, self._cam, self.obs.sphere
        off = self.offsets_m[j]
        X = p[k] + off[:, None] * d[k]
        Rc = R[c]
        RX = (Rc @ X[:, :, None])[:, :, 0]
        Xs = (self._A @ (RX + t[c])[:, :, None])[:, :, 0] + self._b
        px, Jp = project(Xs, self._table)
        assert Jp is not None
        r = (px - self.obs.px).ravel()
        M = Jp @ self._A
        Jpt = M @ Rc  # d r / d p
        proj = (np.eye(3) - d[:, :, None] * d[:, None, :]) / vn[:, :, None]
        tang = proj @ np.stack([self._e1, self._e2], axis=2)
        Jab = (Jpt @ tang[k]) * off[:, None, None]
        nf = self._n_free_obs
        blocks_fixed = np.concatenate([Jpt[nf:], Jab[nf:]], axis=2)
        if nf:
            fcam = self._fc[:nf]
            Jl = _left_jacobian(w)[fcam]
            Jw = -(M[:nf] @ _skew(RX[:nf]) @ Jl)
            blocks_free = np.concatenate([Jw, M[:nf], Jpt[:nf], Jab[:nf]], axis=2)
            data = np.concatenate([blocks_free.ravel(), blocks_fixed.ravel()])
        else:
            data = blocks_fixed.ravel()
        J = sp.csr_matrix((data, self._indices, self._indptr), shape=(len(r), self.n_params))
        self._cache.update(key=key, r=r, J=J)
        return r, J

    def fun(self, x: np.ndarray) -> np.ndarray:
        return self._evaluate(x)[0]

    def jac(self, x: np.ndarray) -> sp.csr_matrix:
        return self._evaluate(x)[1]

    def sparsity(self) -> sp.csr_matrix:
        """The Jacobian's structure, as ``least_squares(jac_sparsity=...)`` takes it."""
        data = np.ones(len(self._indices), dtype=np.int8)
        return sp.csr_matrix(
            (data, self._indices, self._indptr), shape=(2 * len(self.obs), self.n_params)
        )


def refine(
    state: RigState,
    obs: FlatObservations,
    sensors: SensorModels,
    offsets_m: np.ndarray,
    *,
    free_cameras: tuple[int, ...],
    loss: str,
    loss_scale_px: float,
    max_nfev: int,
    tol: float = 1e-8,
) -> tuple[RigState, int]:
    """One robust least-squares solve over the free cameras and every set ``obs`` mentions."""
    sets = np.unique(obs.set_index)
    problem = BundleProblem(state, obs, sensors, offsets_m, sets, free_cameras)
    res = least_squares(
        problem.fun,
        problem.x0(),
        jac=problem.jac,
        method="trf",
        x_scale="jac",
        loss=loss,
        f_scale=loss_scale_px,
        max_nfev=max_nfev,
        ftol=tol,
        xtol=tol,
        gtol=tol,
        tr_solver="lsmr",
    )
    log.debug(
        "bundle: %d params, %d residuals, %d evaluations, cost %.4g (%s)",
        problem.n_params,
        len(res.fun),
        res.nfev,
        res.cost,
        res.message,
    )
    return problem.apply(res.x), int(res.nfev)


def supported_sets(obs: FlatObservations, use: np.ndarray, n_sets: int) -> np.ndarray:
    """(N,) bool: sets where at least two sensors keep at least two spheres each, enough to fix
    the wand's 5 degrees of freedom."""
    k, s = obs.set_index[use], obs.sensor[use]
    n_sensors = int(obs.sensor.max()) + 1 if len(obs) else 1
    per = np.bincount(k * n_sensors + s, minlength=n_sets * n_sensors).reshape(n_sets, n_sensors)
    return (per >= 2).sum(axis=1) >= 2


def cutoff_px(norms: np.ndarray, schedule_px: float, sigmas: float) -> float:
    """The cut-off of one round: the schedule's value, but never below ``sigmas`` robust standard
    deviations of the current residuals (the median of a 2-D Gaussian's norm is 1.1774 sigma)."""
    if not len(norms):
        return schedule_px
    return max(schedule_px, sigmas * float(np.median(norms)) / 1.1774)


@dataclass(frozen=True)
class Round:
    """One outlier-rejection round: the cut-off (the largest over the sensors), observations
    used and left out, sets solved for, and solver evaluations."""

    cutoff_px: float
    observations: int
    rejected: int
    sets: int
    evaluations: int


def adjust(
    state: RigState,
    obs: FlatObservations,
    sensors: SensorModels,
    offsets_m: np.ndarray,
    *,
    free_cameras: tuple[int, ...],
    cutoffs_px: tuple[float, ...],
    cutoff_sigmas: float,
    loss: str,
    loss_scale_px: float,
    max_nfev: int,
) -> tuple[RigState, np.ndarray, list[Round]]:
    """Robust bundle adjustment with iterative outlier rejection (anipose's shrinking cut-off):
    before each solve, observations whose residual exceeds the round's cut-off are left out (and
    earlier rejections come back if they now fit). The cut-off's noise floor is taken per
    sensor, so a camera that starts further off keeps its observations until it has moved in.
    Returns the state, the (M,) inlier mask of the last solve, and one record per round."""
    n_sets, n_sensors = len(state.p), len(sensors.A)
    rounds: list[Round] = []
    use = np.zeros(len(obs), bool)
    for i, schedule in enumerate(cutoffs_px):
        norms = np.linalg.norm(residuals(state, obs, sensors, offsets_m), axis=1)
        finite = np.isfinite(norms)
        basis = finite & (use if i else finite)
        cuts = np.array(
            [
                cutoff_px(norms[basis & (obs.sensor == s)], schedule, cutoff_sigmas)
                for s in range(n_sensors)
            ]
        )
        use = finite & (norms <= cuts[obs.sensor])
        use &= supported_sets(obs, use, n_sets)[obs.set_index]
        if not use.any():
            break
        sub = obs.subset(use)
        last = i == len(cutoffs_px) - 1
        state, nfev = refine(
            state,
            sub,
            sensors,
            offsets_m,
            free_cameras=free_cameras,
            loss=loss,
            loss_scale_px=loss_scale_px,
            max_nfev=max_nfev,
            tol=1e-10 if last else 1e-6,
        )
        n_sets_used = len(np.unique(sub.set_index))
        rounds.append(
            Round(float(cuts.max()), int(use.sum()), int((finite & ~use).sum()), n_sets_used, nfev)
        )
        log.info(
            "bundle round %d: cut-off %.2f px (largest over sensors), %d observations, "
            "%d left out, %d sets, %d evaluations",
            i + 1,
            cuts.max(),
            rounds[-1].observations,
            rounds[-1].rejected,
            n_sets_used,
            nfev,
        )
    return state, use, rounds


def residual_stats(errors: np.ndarray, prefix: str = "reprojection_px") -> dict[str, object]:
    """Mean, RMS, median and 95th percentile of (M,) residual norms, keyed for the TOML file."""
    if not len(errors):
        return {f"{prefix}_{k}": float("nan") for k in ("mean", "rms", "median", "p95")}
    return {
        f"{prefix}_mean": float(np.mean(errors)),
        f"{prefix}_rms": float(np.sqrt(np.mean(errors**2))),
        f"{prefix}_median": float(np.median(errors)),
        f"{prefix}_p95": float(np.percentile(errors, 95)),
    }


def sensor_stats(
    obs: FlatObservations, inlier: np.ndarray, res: np.ndarray, sensor: int
) -> dict[str, float]:
    """One sensor's residual statistics and counts: sets it saw the wand in, sets it
    contributed to (at least one inlier sphere), sets it lost entirely, spheres kept and cut."""
    mine = obs.sensor == sensor
    errors = np.linalg.norm(res[mine & inlier], axis=1)
    seen = len(np.unique(obs.set_index[mine]))
    used = len(np.unique(obs.set_index[mine & inlier]))
    stats = {k: float(v) for k, v in residual_stats(errors).items()}  # type: ignore[arg-type]
    stats |= {
        "frames_seen": float(seen),
        "frames_used": float(used),
        "frames_rejected": float(seen - used),
        "points_used": float((mine & inlier).sum()),
        "points_rejected": float((mine & ~inlier).sum()),
    }
    return stats
