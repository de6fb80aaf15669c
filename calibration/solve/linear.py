"""The linear start of the rig solve: metric stereo triangulation, rigid alignment, spanning tree.

Every ZED X measures the wand in metres on its own (factory intrinsics and stereo pose), so two
cameras that see the same sets relate by a rigid transform of their triangulated sphere centres:
Kabsch/Umeyama without scale, made robust by RANSAC over sets. Cameras chain to the reference
along a maximum spanning tree of the co-visibility graph. A camera without a usable stereo pair
(one sensor blocked or missing) starts from an essential matrix with its tree parent instead, its
scale taken from the wand's known length.

Conventions: normalised coordinates are undistorted ``(x/z, y/z)``; a pose ``(R, t)`` maps
``x_b = R @ x_a + t``; arrays carry their shapes in the docstrings.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.observations import WandObservations
from calibration.solve.bundle import FlatObservations, RigState, SensorModels
from protocol.camera import undistort_to_normalized

log = logging.getLogger(__name__)


def triangulate(
    P: np.ndarray, xn: np.ndarray, mask: np.ndarray, *, iterations: int = 3
) -> np.ndarray:
    """Points seen in several views: linear DLT, then Gauss-Newton on the normalised error.

    ``P`` (M, V, 3, 4) or (V, 3, 4): each view's projection into normalised coordinates;
    ``xn`` (M, V, 2) observations; ``mask`` (M, V) which views count. Returns (M, 3), NaN where
    fewer than two views count.
    """
    xn = np.asarray(xn, dtype=np.float64)
    m, v = mask.shape
    Pm = np.broadcast_to(P, (m, v, 3, 4))
    w = mask[..., None].astype(np.float64)
    x = np.where(mask[..., None], xn, 0.0)
    rows = np.concatenate(
        [
            x[..., 0:1] * Pm[:, :, 2, :] - Pm[:, :, 0, :],
            x[..., 1:2] * Pm[:, :, 2, :] - Pm[:, :, 1, :],
        ],
        axis=1,
    ) * np.concatenate([w, w], axis=1)
    ok = mask.sum(axis=1) >= 2
    out = np.full((m, 3), np.nan)
    if not ok.any():
        return out
    _, _, vt = np.linalg.svd(rows[ok])
    h = vt[:, -1, :]
    X = h[:, :3] / h[:, 3:4]
    Pk, xk, wk = Pm[ok], xn[ok], mask[ok].astype(np.float64)
    R, t = Pk[..., :3], Pk[..., 3]
    for _ in range(iterations):
        c = np.einsum("mvij,mj->mvi", R, X) + t
        z = c[..., 2:3]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        proj = c[..., :2] / z
        r = np.where(wk[..., None] > 0, proj - np.nan_to_num(xk), 0.0)
        dproj = np.zeros((*c.shape[:2], 2, 3))
        dproj[..., 0, 0] = dproj[..., 1, 1] = 1.0 / z[..., 0]
        dproj[..., :, 2] = -proj / z
        J = np.einsum("mvab,mvbc->mvac", dproj, R) * wk[..., None, None]
        H = np.einsum("mvab,mvac->mbc", J, J) + 1e-12 * np.eye(3)
        g = np.einsum("mvab,mva->mb", J, r)
        X = X - np.linalg.solve(H, g[..., None])[..., 0]
    out[ok] = X
    return out


def fit_wand(points: np.ndarray, offsets_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best rigid wand through (K, 3, 3) sphere centres; ``offsets_m`` (3,) sum to zero.

    Returns (K, 3) centroid and (K, 3) unit direction (first towards last sphere).
    """
    centre = points.mean(axis=1)
    d = np.einsum("j,kjc->kc", offsets_m, points - centre[:, None, :])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return centre, d


def kabsch(a: np.ndarray, b: np.ndarray, weights: np.ndarray | None = None) -> tuple:
    """Rigid ``(R, t)`` with ``b ≈ R @ a + t`` for (M, 3) point sets, least squares."""
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    H = ((a - ca) * w[:, None]).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def spread_m(points: np.ndarray) -> float:
    """RMS extent of (M, 3) points in their second principal direction: ~0 for a line or a dot."""
    p = points - points.mean(axis=0)
    s = np.linalg.svd(p, compute_uv=False)
    return float(s[1] / np.sqrt(len(p)))


@dataclass(frozen=True)
class Alignment:
    R: np.ndarray  # (3, 3): x_b = R @ x_a + t
    t: np.ndarray  # (3,)
    inlier_sets: np.ndarray  # (K,) bool over the sets given
    rms_m: float


def ransac_kabsch(
    a: np.ndarray,
    b: np.ndarray,
    *,
    threshold_m: float,
    iterations: int,
    min_spread_m: float,
    rng: np.random.Generator,
) -> Alignment | None:
    """Align (K, 3, 3) sphere centres triangulated by camera a to the same sets from camera b.

    Stereo depth error grows with the square of depth, so a set's tolerance grows with
    ``(depth / 2 m)²``. Returns None when no sample spans a plane (degenerate: the wand never
    moved, or moved along one line).
    """
    k = len(a)
    depth = np.maximum(a[..., 2].max(axis=1), b[..., 2].max(axis=1))
    tol = threshold_m * np.maximum(1.0, (depth / 2.0) ** 2)
    weight = 1.0 / np.maximum(1.0, (depth / 2.0) ** 2) ** 2

    def errors(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.linalg.norm(a @ R.T + t - b, axis=2).max(axis=1)

    best: np.ndarray | None = None
    for _ in range(iterations):
        pick = rng.choice(k, size=min(3, k), replace=False)
        pa, pb = a[pick].reshape(-1, 3), b[pick].reshape(-1, 3)
        if spread_m(pa) < 0.05:
            continue
        R, t = kabsch(pa, pb)
        inl = errors(R, t) < tol
        if best is None or inl.sum() > best.sum():
            best = inl
    if best is None or best.sum() < 3:
        return None
    inl = best
    for _ in range(3):
        pa, pb = a[inl].reshape(-1, 3), b[inl].reshape(-1, 3)
        if spread_m(pa) < min_spread_m:
            return None
        R, t = kabsch(pa, pb, np.repeat(weight[inl], 3))
        inl = errors(R, t) < tol
        if inl.sum() < 3:
            return None
    res = np.linalg.norm(a[inl] @ R.T + t - b[inl], axis=2)
    return Alignment(R, t, inl, float(np.sqrt(np.mean(res**2))))


def essential_pose(
    xa: np.ndarray,
    xb: np.ndarray,
    *,
    threshold: float,
    wand_length_m: float,
    first_last: tuple[int, int] = (0, 2),
) -> Alignment | None:
    """Relative pose of two single sensors from (K, 3, 2) normalised wand observations.

    ``x_b = R @ x_a + t``; the essential matrix leaves the scale free, so the translation is
    scaled until the triangulated first-to-last sphere distance has the wand's median length.
    ``threshold`` is the RANSAC tolerance in normalised units (pixels / focal length).
    """
    k = len(xa)
    pa, pb = xa.reshape(-1, 2), xb.reshape(-1, 2)
    if len(pa) < 8 or spread_m(np.c_[pa, np.zeros(len(pa))]) < 1e-3:
        return None
    E, mask = cv2.findEssentialMat(
        pa, pb, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=threshold
    )
    if E is None or E.shape[0] < 3:
        return None
    n_good, R, t, mask = cv2.recoverPose(E[:3], pa, pb, np.eye(3), mask=mask)
    if n_good < 0.5 * len(pa):
        return None
    t = t.ravel()
    P = np.stack([np.eye(3, 4), np.c_[R, t]])
    X = triangulate(P, np.stack([pa, pb], axis=1), np.ones((len(pa), 2), bool)).reshape(k, 3, 3)
    good = mask.ravel().reshape(k, 3).all(axis=1) & np.isfinite(X).all(axis=(1, 2))
    if good.sum() < 3:
        return None
    lengths = np.linalg.norm(X[good, first_last[1]] - X[good, first_last[0]], axis=1)
    scale = wand_length_m / float(np.median(lengths))
    return Alignment(R, t * scale, good, float("nan"))


def maximum_spanning_tree(weight: np.ndarray, root: int) -> np.ndarray:
    """Prim on a symmetric (C, C) edge weight (0 = no edge). Returns each node's parent:
    -1 for the root, -2 for nodes that cannot be reached."""
    c = len(weight)
    parent = np.full(c, -2)
    parent[root] = -1
    in_tree = np.zeros(c, bool)
    in_tree[root] = True
    while True:
        cand = np.where(in_tree[:, None] & ~in_tree[None, :], weight, 0)
        i, j = np.unravel_index(np.argmax(cand), cand.shape)
        if cand[i, j] <= 0:
            return parent
        parent[j] = i
        in_tree[j] = True


def tree_order(parent: np.ndarray) -> list[int]:
    """Nodes in an order where every parent comes before its children (reachable ones only)."""
    order = [int(np.where(parent == -1)[0][0])]
    while True:
        new = [i for i in range(len(parent)) if parent[i] in order and i not in order]
        if not new:
            return order
        order += new


# ---- from wand observations to a start ----------------------------------------------------


def normalised(obs: WandObservations) -> np.ndarray:
    """(N, S, 3, 2) undistorted normalised coordinates of every observation, NaN where unseen."""
    out = np.full(obs.points_px.shape, np.nan)
    for s, key in enumerate(obs.sensors):
        pts = obs.points_px[:, s].reshape(-1, 2)
        ok = np.isfinite(pts).all(axis=1)
        if ok.any():
            flat = out[:, s].reshape(-1, 2)
            flat[ok] = undistort_to_normalized(pts[ok], obs.intrinsics(key))
            out[:, s] = flat.reshape(-1, 3, 2)
    return out


def projection_matrices(state: RigState, sensors: SensorModels) -> np.ndarray:
    """(S, 3, 4) world-to-normalised projection of every sensor."""
    cam = np.arange(len(sensors.A)) // 2
    Rs = sensors.A @ state.R[cam]
    ts = (sensors.A @ state.t[cam][:, :, None])[:, :, 0] + sensors.b
    return np.concatenate([Rs, ts[:, :, None]], axis=2)


@dataclass(frozen=True)
class StereoWand:
    """One camera's own triangulation of the wand, in its left sensor's frame."""

    points: np.ndarray  # (N, 3, 3), NaN where both sensors did not see all three spheres
    fits: np.ndarray  # (N,) bool: the triangulation reprojects within the tolerance

    def distances(self) -> np.ndarray:
        """(N, 3) first-middle, middle-last, first-last distances in metres, NaN if unknown."""
        p = self.points
        pairs = ((0, 1), (1, 2), (0, 2))
        return np.stack([np.linalg.norm(p[:, b] - p[:, a], axis=1) for a, b in pairs], 1)

    def distances_mm(self) -> np.ndarray:
        """(n, 3) distances of the sets whose triangulation fits, in millimetres."""
        return 1000 * self.distances()[self.fits]

    def depth_ratio(self, centres: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
        """Median over spheres of (depth from this stereo pair) / (depth in a solution whose
        (N, 3, 3) ``centres`` this camera sees through world-to-left ``R``, ``t``).

        The factory baseline sets the stereo depths and the wand the solution's scale, so 1.0
        means they agree. A median of depth ratios is unbiased, where one of noisy lengths is
        not (a length's error adds in quadrature)."""
        ok = self.fits & np.isfinite(centres).all(axis=(1, 2))
        if ok.sum() < 3:
            return float("nan")
        z_solved = (centres[ok] @ R.T + t)[..., 2]
        return float(np.median(self.points[ok, :, 2] / z_solved))


def stereo_wand(
    xn: np.ndarray, seen: np.ndarray, sensors: SensorModels, c: int, max_error_px: float
) -> StereoWand:
    """Camera ``c`` triangulates the wand from its own left and right sensors (factory stereo).
    ``xn`` (N, S, 3, 2) normalised observations, ``seen`` (N, S) all three spheres seen."""
    n = len(xn)
    both = seen[:, 2 * c] & seen[:, 2 * c + 1]
    points = np.full((n, 3, 3), np.nan)
    fits = np.zeros(n, bool)
    if both.sum() == 0:
        return StereoWand(points, fits)
    P = np.stack([np.eye(3, 4), np.c_[sensors.A[2 * c + 1], sensors.b[2 * c + 1]]])
    x = xn[both][:, 2 * c : 2 * c + 2].transpose(0, 2, 1, 3).reshape(-1, 2, 2)
    X = triangulate(P, x, np.ones((len(x), 2), bool))
    proj = (P[None, :, :, :3] @ X[:, None, :, None])[..., 0] + P[:, :, 3]
    err = np.linalg.norm(proj[..., :2] / proj[..., 2:] - x, axis=2).max(axis=1)
    f = sensors.intrinsics[2 * c].fx_px
    points[both] = X.reshape(-1, 3, 3)
    fits[both] = (f * err.reshape(-1, 3) < max_error_px).all(axis=1) & (points[both, :, 2] > 0).all(
        axis=1
    )
    return StereoWand(points, fits)


class LinkError(Exception):
    """Camera ``child`` could not be placed relative to ``parent``: ``reason`` is "few" (too
    few shared sets) or "degenerate" (the shared wand positions do not fix a pose)."""

    def __init__(self, child: int, parent: int, reason: str) -> None:
        super().__init__(f"camera {child} from {parent}: {reason}")
        self.child, self.parent, self.reason = child, parent, reason


def chain_poses(
    parent: np.ndarray,
    seen: np.ndarray,
    xn: np.ndarray,
    stereo: list[StereoWand],
    sensors: SensorModels,
    expected_m: np.ndarray,
    names: list[str],
    *,
    min_sets: int,
    ransac_threshold_m: float,
    ransac_iterations: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """World(= root's left sensor)-to-left poses (C, 3, 3), (C, 3) of every camera in the tree,
    and how each was found. ``expected_m`` (3,) the wand's distances. Raises ``LinkError``."""
    n_cams = len(parent)
    root = int(np.flatnonzero(parent == -1)[0])
    R, t = np.zeros((n_cams, 3, 3)), np.zeros((n_cams, 3))
    R[root] = np.eye(3)
    how = {root: "reference"}
    # a camera's own triangulations that give the wand back, to within 15 % of its length
    good = [
        s.fits & (np.abs(s.distances() - expected_m).max(axis=1) < 0.15 * expected_m[2])
        for s in stereo
    ]
    for c in tree_order(parent)[1:]:
        p = int(parent[c])
        both = good[p] & good[c]
        align = None
        if both.sum() >= min_sets:
            align = ransac_kabsch(
                stereo[p].points[both],
                stereo[c].points[both],
                threshold_m=ransac_threshold_m,
                iterations=ransac_iterations,
                min_spread_m=0.05,
                rng=rng,
            )
        if align is not None:
            rel_R, rel_t = align.R, align.t
            how[c] = f"Kabsch from {names[p]} ({int(align.inlier_sets.sum())} sets)"
        else:
            # essential matrix between the two single sensors that share the most sets
            pairs = [(a, b) for a in (2 * p, 2 * p + 1) for b in (2 * c, 2 * c + 1)]
            a, b = max(pairs, key=lambda ab: int((seen[:, ab[0]] & seen[:, ab[1]]).sum()))
            common = seen[:, a] & seen[:, b]
            if common.sum() < min_sets:
                raise LinkError(c, p, "few")
            found = essential_pose(
                xn[common, a],
                xn[common, b],
                threshold=1.0 / sensors.intrinsics[b].fx_px,
                wand_length_m=float(expected_m[2]),
            )
            if found is None:
                raise LinkError(c, p, "degenerate")
            # sensor b = R sensor a + t, sensor = A left + b  ->  left c from left p
            rel_R = sensors.A[b].T @ found.R @ sensors.A[a]
            rel_t = sensors.A[b].T @ (found.R @ sensors.b[a] + found.t - sensors.b[b])
            how[c] = f"essential matrix with {names[p]} ({int(found.inlier_sets.sum())} sets)"
        R[c], t[c] = rel_R @ R[p], rel_R @ t[p] + rel_t
    return R, t, how


def init_wands(
    state: RigState, sets: np.ndarray, xn: np.ndarray, sensors: SensorModels, offsets_m: np.ndarray
) -> None:
    """Triangulate each set's spheres from every sensor with the current poses, and fit a rigid
    wand into ``state``. Sets where a sphere is seen by fewer than two sensors stay as they are."""
    if not len(sets):
        return
    P = projection_matrices(state, sensors)
    x = xn[sets].transpose(0, 2, 1, 3).reshape(-1, len(P), 2)
    X = triangulate(P, x, np.isfinite(x).all(axis=2)).reshape(-1, 3, 3)
    ok = np.isfinite(X).all(axis=(1, 2))
    p, d = fit_wand(X[ok], offsets_m)
    state.p[sets[ok]], state.d[sets[ok]] = p, d


def free_lengths_mm(
    state: RigState,
    obs: FlatObservations,
    use: np.ndarray,
    xn: np.ndarray,
    sensors: SensorModels,
) -> np.ndarray:
    """First-to-last wand lengths (mm) from unconstrained triangulation of the two end spheres,
    from the observations in ``use``, in sets where two or more cameras (not only one camera's
    stereo pair) see both ends."""
    n_sets, n_sens = xn.shape[:2]
    mask = np.zeros((n_sets, 3, n_sens), bool)
    mask[obs.set_index[use], obs.sphere[use], obs.sensor[use]] = True
    ncam = mask.reshape(n_sets, 3, -1, 2).any(axis=3).sum(axis=2)
    sets = np.flatnonzero((ncam[:, [0, 2]] >= 2).all(axis=1))
    if not len(sets):
        return np.zeros(0)
    P = projection_matrices(state, sensors)
    x = xn[sets][:, :, [0, 2]].transpose(0, 2, 1, 3).reshape(-1, n_sens, 2)
    X = triangulate(P, x, mask[sets][:, [0, 2]].reshape(-1, n_sens)).reshape(-1, 2, 3)
    return 1000 * np.linalg.norm(X[:, 1] - X[:, 0], axis=1)
