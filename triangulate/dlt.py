"""Robust confidence-weighted DLT, batched over every joint of every person at once (seed sec. 4.2.1).

One call triangulates N points seen by up to C cameras: the 2C x 4 DLT systems of all points
are reduced to their 4 x 4 normal matrices with one batched matmul and solved together
(inhomogeneous form, X_4 = 1). A second solve reweights every row by the inverse projective
depth of the first estimate, which turns the algebraic error into (first-order) pixel error
(Hartley & Sturm's iterative linear method). Views whose reprojection error exceeds a
threshold are dropped one at a time (the worst first) and the point is re-triangulated, as
long as ``min_views`` remain. Per point the result carries the mean reprojection error, the
number of views used, the mean 2D confidence of those views and a positional standard deviation
from the Gauss-Newton covariance ``sigma^2 (J^T J)^-1``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields

import numpy as np

from triangulate.geometry import check_shape

_EPS_EYE = 1e-12 * np.eye(3)


# adjugate of a symmetric 3x3 matrix in flat (row*3+col) indices: adj[k] = m[A]*m[B] - m[C]*m[D],
# the cofactors c00 c01 c02 / c01 c11 c12 / c02 c12 c22 (upper-triangle entries read where possible)
_ADJ_AC = np.array([[4, 2, 1, 2, 0, 1, 1, 1, 0], [5, 1, 2, 1, 2, 0, 2, 0, 1]])
_ADJ_BD = np.array([[8, 5, 5, 5, 8, 2, 5, 2, 4], [5, 8, 4, 8, 2, 5, 4, 5, 1]])


def _sym3_adj_det(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Adjugate (N,9) (flat, row-major) and determinant (N,) of symmetric 3x3 matrices M (N,3,3)."""
    m = M.reshape(len(M), 9)
    ab_cd = m[:, _ADJ_AC] * m[:, _ADJ_BD]  # (N,2,9): the two products of each cofactor
    adj = ab_cd[:, 0] - ab_cd[:, 1]
    q = m[:, :3] * adj[:, :3]  # det = m00 c00 + m01 c01 + m02 c02 (expansion along the first row)
    det = q[:, 0] + q[:, 1]
    det += q[:, 2]
    return adj, det


def _sym3_solve(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x (N,3) with M x = -b for symmetric positive definite M (N,3,3), b (N,3): the adjugate in
    closed form, a dozen array operations whatever N. On these well-scaled 3x3 normal matrices it
    agrees with LAPACK's LU (np.linalg.solve) to ~1e-15 relative and avoids its per-matrix call
    overhead (the frame's largest fixed cost)."""
    adj, det = _sym3_adj_det(M)
    r = -1.0 / det  # det >= 1e-36 > 0: M = A + 1e-12 I with A = R^T R positive semi-definite
    p = adj.reshape(len(M), 3, 3) * b[:, None, :]
    x = p[..., 0] + p[..., 1]
    x += p[..., 2]
    x *= r[:, None]
    return x


def _sym3_inv_trace(M: np.ndarray) -> np.ndarray:
    """trace(M^-1) (N,) of symmetric 3x3 matrices M (N,3,3), in closed form (see ``_sym3_solve``)."""
    adj, det = _sym3_adj_det(M)
    return (adj[:, 0] + adj[:, 4] + adj[:, 8]) / det


def _reject_unknown(cls, d: dict) -> dict:
    valid = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - valid)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown keys {unknown}; valid keys: {sorted(valid)}")
    return d


@dataclass(frozen=True)
class DLTConfig:
    """Triangulation settings.

    min_views: fewest views that may form a 3D joint.
    min_score: 2D joints with a lower confidence are treated as unseen.
    max_reproj_px: views above this reprojection error are rejected (worst first) and the joint is
      re-triangulated; a joint that still exceeds it with ``min_views`` views is dropped.
    max_rejections: at most this many views are rejected per joint.
    noise_px: prior 2D noise used for ``std_m`` (the larger of it and the RMS residual is used).
    max_std_m: joints with a larger positional std (e.g. nearly collinear rays) are dropped.
    """

    min_views: int = 2
    min_score: float = 0.05
    max_reproj_px: float = 12.0
    max_rejections: int = 4
    noise_px: float = 2.0
    max_std_m: float = 0.15

    def __post_init__(self) -> None:
        if self.min_views < 2:
            raise ValueError(f"DLTConfig.min_views must be >= 2 (a ray is no point), got {self.min_views}.")
        if self.max_reproj_px <= 0 or self.noise_px <= 0 or self.max_std_m <= 0:
            raise ValueError("DLTConfig: max_reproj_px, noise_px and max_std_m must be positive.")

    @classmethod
    def from_dict(cls, d: dict) -> DLTConfig:
        return cls(**_reject_unknown(cls, d))


@dataclass(frozen=True)
class Triangulated:
    """Per-point triangulation result (N points, C cameras)."""

    xyz_m: np.ndarray  # (N,3) NaN where not triangulated
    reproj_err_px: np.ndarray  # (N,) mean reprojection error over the views used
    n_views: np.ndarray  # (N,) int
    score: np.ndarray  # (N,) mean 2D confidence of the views used
    std_m: np.ndarray  # (N,) positional std (per axis, RMS over axes)
    used: np.ndarray  # (C,N) bool


def normalise_P(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scale each P so its third row has a unit rotation part, then normalise image coordinates.

    Returns ``Pn (C,3,4)``, the principal point ``c (C,2)`` and the scale ``s (C,)`` (about the focal
    length) such that ``xn = (x - c) / s`` are the coordinates ``Pn`` projects to. With zero skew
    these are exact: ``c = (P1.P3, P2.P3)``, ``s = sqrt(|P1|^2 - c_x^2)`` on the 3x3 part.
    """
    P = np.asarray(P, dtype=np.float64)
    check_shape("P", P, (None, 3, 4))
    P = P / np.linalg.norm(P[:, 2, :3], axis=1)[:, None, None]
    P = P * np.sign(np.linalg.det(P[:, :, :3]))[:, None, None]  # positive depth in front of the camera
    c = np.stack([np.einsum("ci,ci->c", P[:, 0, :3], P[:, 2, :3]),
                  np.einsum("ci,ci->c", P[:, 1, :3], P[:, 2, :3])], 1)
    s = np.sqrt(np.maximum(np.einsum("ci,ci->c", P[:, 0, :3], P[:, 0, :3]) - c[:, 0] ** 2, 1e-12))
    T = np.zeros((len(P), 3, 3))
    T[:, 0, 0] = T[:, 1, 1] = 1.0 / s
    T[:, 0, 2], T[:, 1, 2] = -c[:, 0] / s, -c[:, 1] / s
    T[:, 2, 2] = 1.0
    return T @ P, c, s


class Triangulator:
    """Precomputed, normalised projection matrices of a rig; ``__call__`` triangulates points."""

    def __init__(self, P: np.ndarray, config: DLTConfig | None = None):
        self.P = np.asarray(P, dtype=np.float64)
        check_shape("P", self.P, (None, 3, 4))
        self.config = config or DLTConfig()
        self.Pn, self.c, self.s = normalise_P(self.P)
        self.n_cams = len(self.P)
        # per-rig constants of the hot loop, shaped for broadcasting once
        self._P0, self._P1, self._P2 = (np.ascontiguousarray(self.Pn[:, None, k, :]) for k in range(3))
        # (views, not copies: matmul's result can depend on the operands' memory layout)
        self._Pn2_3T, self._Pn2_4 = self.Pn[:, 2, :3].T, self.Pn[:, None, 2, 3]
        self._Pn33, self._Pn3_4 = self.Pn[:, :, :3], self.Pn[:, :, 3:4]
        self._c, self._s = self.c[:, None], self.s[:, None, None]
        self._s2 = self.s[:, None] ** 2

    def _solve(self, xyn, w):
        """Weighted linear solve. xyn (C,N,2), w (C,N) (0 = unused). Returns X (N,3) and the normal
        matrix M (N,3,3) (with depth-reweighted rows: the Gauss-Newton information in normalised units)."""
        C, N = w.shape
        R = np.empty((2 * C, N, 4))
        U, V = R[:C], R[C:]
        np.multiply(xyn[..., 0:1], self._P2, out=U)  # (C,N,4)
        U -= self._P0
        U *= w[..., None]
        np.multiply(xyn[..., 1:2], self._P2, out=V)
        V -= self._P1
        V *= w[..., None]
        R = R.transpose(1, 0, 2)  # (N,2C,4)
        A = np.matmul(R.transpose(0, 2, 1), R)  # (N,4,4)
        M = A[:, :3, :3] + _EPS_EYE
        return _sym3_solve(M, A[:, :3, 3]), M

    def __call__(self, xy_px: np.ndarray, weights: np.ndarray | None = None) -> Triangulated:
        """Triangulate N points. xy_px: (C,N,2) undistorted pixels, NaN = unseen; weights: (C,N) scores."""
        cfg = self.config
        xy = np.asarray(xy_px, dtype=np.float64)
        C = self.n_cams
        check_shape("xy_px", xy, (C, None, 2))
        N = xy.shape[1]
        w0 = np.ones(xy.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
        check_shape("weights", w0, (C, N))
        seen = np.isfinite(xy).all(-1) & (w0 >= cfg.min_score) & np.isfinite(w0)
        w0 = np.where(seen, w0, 0.0)
        xyn = (xy - self._c) / self._s
        xyn[~seen] = 0.0
        used = seen.copy()
        ar = np.arange(N)
        X, info = self._solve(xyn, w0)  # algebraic first guess
        idx = slice(None)  # all points (a view, no gather) until the first rejection
        for it in range(cfg.max_rejections + 1):
            # reweight by inverse projective depth: rows then measure (normalised) pixel error;
            # after a rejection only the points that lost a view are solved again
            depth = (X[idx] @ self._Pn2_3T).T + self._Pn2_4
            u = used[:, idx] & (depth > 1e-6)
            used[:, idx] = u
            w = np.where(u, w0[:, idx] / np.where(u, depth, 1.0), 0.0)
            X[idx], info[idx] = self._solve(xyn[:, idx], w)
            proj = (np.matmul(self._Pn33, X.T) + self._Pn3_4).transpose(0, 2, 1)  # (C,N,3)
            depth = proj[..., 2]
            used &= depth > 1e-6
            safe = np.where(depth > 1e-6, depth, 1.0)[..., None]
            res = (proj[..., :2] / safe - xyn) * self._s
            err = np.where(used, np.sqrt((res ** 2).sum(-1)), -np.inf)  # (C,N) pixels
            if it == cfg.max_rejections:
                break
            worst = err.argmax(0)
            drop = (err[worst, ar] > cfg.max_reproj_px) & (used.sum(0) > cfg.min_views)
            if not drop.any():
                break
            idx = ar[drop]
            used[worst[idx], idx] = False
        n_views = used.sum(0)
        err_used = np.where(used, err, 0.0)
        reproj = err_used.sum(0) / np.maximum(n_views, 1)
        # covariance sigma^2 (J^T W J)^-1 from the last solve's normal matrix: its rows are the
        # Jacobian d(normalised pixel)/dX weighted by the confidences; back to pixels with the mean
        # focal scale and mean squared confidence of the views used
        nv = np.maximum(n_views, 1)
        w2 = np.where(used, w0 ** 2, 0.0).sum(0) / nv
        s2 = np.where(used, self._s2, 0.0).sum(0) / nv
        rms = np.sqrt((err_used ** 2).sum(0) / nv)
        sigma = np.maximum(cfg.noise_px, rms)
        tr = _sym3_inv_trace(info)
        std = sigma * np.sqrt(np.maximum(tr, 0) * w2 / np.maximum(s2, 1e-12) / 3.0)
        max_err = err_used.max(0)
        ok = (n_views >= cfg.min_views) & (max_err <= cfg.max_reproj_px) & (std <= cfg.max_std_m) \
            & np.isfinite(X).all(1)
        score = np.where(used, w0, 0.0).sum(0) / np.maximum(n_views, 1)
        nan = np.float64(np.nan)
        return Triangulated(
            xyz_m=np.where(ok[:, None], X, nan), reproj_err_px=np.where(ok, reproj, nan),
            n_views=np.where(ok, n_views, 0).astype(np.int16), score=np.where(ok, score, 0.0),
            std_m=np.where(ok, std, nan), used=used & ok[None])


def triangulate_dlt(P: np.ndarray, xy_px: np.ndarray, weights: np.ndarray | None = None,
                    min_views: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Plain weighted DLT (no rejection). P: (C,3,4); xy_px: (C,N,2), NaN = unseen; weights: (C,N).

    Returns xyz_m (N,3) (NaN where fewer than ``min_views``) and n_views (N,).
    """
    cfg = DLTConfig(min_views=min_views, min_score=0.0, max_reproj_px=1e9, max_rejections=0, max_std_m=1e9)
    r = Triangulator(P, cfg)(xy_px, weights)
    return r.xyz_m, r.n_views


# Plausible limb lengths (metres) by joint-name pair: generous bounds that still catch a joint
# triangulated from mismatched or flipped views.
LIMB_BOUNDS_M = {
    ("left_shoulder", "left_elbow"): (0.12, 0.50), ("right_shoulder", "right_elbow"): (0.12, 0.50),
    ("left_elbow", "left_wrist"): (0.10, 0.45), ("right_elbow", "right_wrist"): (0.10, 0.45),
    ("left_hip", "left_knee"): (0.20, 0.65), ("right_hip", "right_knee"): (0.20, 0.65),
    ("left_knee", "left_ankle"): (0.20, 0.65), ("right_knee", "right_ankle"): (0.20, 0.65),
    ("left_shoulder", "right_shoulder"): (0.15, 0.60), ("left_hip", "right_hip"): (0.08, 0.50),
    ("neck", "pelvis"): (0.25, 0.90), ("nose", "neck"): (0.03, 0.45),
}


def _pairs(joint_names: tuple[str, ...], bounds: dict):
    idx = {n: i for i, n in enumerate(joint_names)}
    pairs = [(idx[a], idx[b], lo, hi) for (a, b), (lo, hi) in bounds.items() if a in idx and b in idx]
    return tuple(np.asarray(v) for v in zip(*pairs, strict=True)) if pairs else None


@functools.cache
def _limb_pairs(joint_names: tuple[str, ...]):
    return _pairs(joint_names, LIMB_BOUNDS_M)


def limb_check(xyz_m: np.ndarray, reproj_err_px: np.ndarray, joint_names: tuple[str, ...],
               bounds: dict | None = None) -> np.ndarray:
    """Plausibility of limb lengths. xyz_m: (M,J,3); reproj_err_px: (M,J).

    For each limb outside its bounds the endpoint with the larger reprojection error is marked.
    Returns a (M,J) bool mask of joints to keep.
    """
    keep = np.ones(xyz_m.shape[:2], bool)
    pairs = _limb_pairs(tuple(joint_names)) if bounds is None else _pairs(tuple(joint_names), bounds)
    if pairs is None:
        return keep
    a, b, lo, hi = pairs
    dv = xyz_m[:, a] - xyz_m[:, b]
    length = np.sqrt(np.add.reduce(dv * dv, axis=-1))  # (M,L), = np.linalg.norm(dv, axis=-1)
    bad = (length < lo) | (length > hi)  # NaN (a missing endpoint) is neither
    if bad.any():
        ea, eb = np.nan_to_num(reproj_err_px[:, a]), np.nan_to_num(reproj_err_px[:, b])
        m, limb = np.nonzero(bad)
        worse = np.where(ea[m, limb] >= eb[m, limb], a[limb], b[limb])
        keep[m, worse] = False
    return keep
