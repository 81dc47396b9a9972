"""Robust confidence-weighted DLT, batched over every joint of every person at once (seed sec. 4.2.1).

One call triangulates N points seen by up to C cameras. Each point's 2C x 4 DLT system (rows
``w (x p3 - p1)``, ``w (y p3 - p2)`` per view) enters only through its 4 x 4 normal matrix, which
is linear in four per-view features ``w^2 (x^2 + y^2), w^2 x, w^2 y, w^2`` with per-rig constant
coefficients (outer products of the projection rows). So the normal matrices of *all* points are
one (9 x 4C) @ (4C x N) matrix product (the 6 distinct entries of the 3 x 3 block and the 3 of the
last column) and are solved together in closed form (inhomogeneous form, X_4 = 1). A second solve
reweights every row by the inverse projective depth of the first estimate, which turns the
algebraic error into (first-order) pixel error (Hartley & Sturm's iterative linear method). Views
whose reprojection error exceeds a threshold are dropped one at a time (the worst first) and the
point is re-triangulated, as long as ``min_views`` remain. Per point the result carries the mean
reprojection error, the number of views used, the mean 2D confidence of those views and a
positional standard deviation from the Gauss-Newton covariance ``sigma^2 (J^T J)^-1``.

Everything runs on (C, N) planes (one row per camera, points along the contiguous axis): a frame
of 4 people x 5 cameras is a few dozen array operations per rejection round whatever N.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from roomcap.core.config import config_from_dict
from roomcap.keypoints.skeletons import HAND_BONES
from roomcap.triangulate.geometry import check_shape

_SCORE, _REPROJ, _STD, _NVIEWS = 4, 5, 6, 7  # rows of ``Triangulator.solve_raw``'s V
_PER_VIEW = 8  # V[_PER_VIEW + c]: the reprojection error in camera c (NaN where that view was not used)
_EPS = 1e-12  # added to the 3x3 normal matrix' diagonal: keeps it positive definite (det > 0)

# the 9 entries of the 4x4 normal matrix that the inhomogeneous solve reads, as (row, col):
# the symmetric 3x3 block m00 m01 m02 m11 m12 m22, then b = (m03, m13, m23)
_NE_ROWS = np.array([0, 0, 0, 1, 1, 2, 0, 1, 2])
_NE_COLS = np.array([0, 1, 2, 1, 2, 2, 3, 3, 3])
# cofactors c00 c01 c02 c11 c12 c22 of a symmetric 3x3 matrix (m00 m01 m02 m11 m12 m22 = 0..5):
# c = m[A] m[B] - m[C] m[D]; _COF[0] = (A, B), _COF[1] = (C, D)
_COF = np.array([[[3, 2, 1, 0, 1, 0], [5, 4, 4, 5, 2, 3]], [[4, 1, 2, 2, 0, 1], [4, 5, 3, 2, 4, 1]]])
_ADJ_FULL = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])  # (i, j) of the 3x3 adjugate -> cofactor row


def _adj_det(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cofactors (6,N) and determinant (N,) of the symmetric 3x3 blocks A[:6] (m00 m01 m02 m11 m12 m22)."""
    g = A[_COF]  # (2,2,6,N)
    p = g[:, 0] * g[:, 1]
    adj = p[0] - p[1]
    det = np.add.reduce(A[:3] * adj[:3], 0)  # expansion along the first row
    return adj, det


def _solve9(A: np.ndarray) -> np.ndarray:
    """X (3,N) with M X = -b for the normal-matrix entries A (9,N) (see ``_NE_ROWS``): the adjugate in
    closed form, a dozen array operations whatever N. On these well-scaled positive definite 3x3
    matrices it agrees with LAPACK's LU (np.linalg.solve) to ~1e-15 relative without its per-matrix
    call overhead."""
    adj, det = _adj_det(A)
    x = np.add.reduce(adj[_ADJ_FULL] * A[None, 6:9], 1)  # (3,N) = adj(M) b
    x *= -1.0 / det  # det >= 1e-36 > 0: M = R^T R + 1e-12 I is positive definite
    return x


def _inv_trace(A: np.ndarray) -> np.ndarray:
    """trace(M^-1) (N,) of the 3x3 blocks of A (9,N)."""
    adj, det = _adj_det(A)
    return (adj[0] + adj[3] + adj[5]) / det


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
        return config_from_dict(cls, d)


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
    c = np.stack(
        [np.einsum("ci,ci->c", P[:, 0, :3], P[:, 2, :3]), np.einsum("ci,ci->c", P[:, 1, :3], P[:, 2, :3])], 1
    )
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
        self.n_cams = C = len(self.P)
        # per-rig constants of the hot loop. Normal matrix of one view (module doc):
        # (x^2 + y^2) p3 p3^T - x (p3 p1^T + p1 p3^T) - y (p3 p2^T + p2 p3^T) + p1 p1^T + p2 p2^T,
        # plus a constant feature row that puts 1e-12 on the 3x3 block's diagonal
        p0, p1, p2 = self.Pn[:, 0], self.Pn[:, 1], self.Pn[:, 2]  # (C,4)

        def sym(a, b):
            o = a[:, :, None] * b[:, None, :]
            return o + o.transpose(0, 2, 1) if a is not b else o

        K = np.stack([sym(p2, p2), -sym(p2, p0), -sym(p2, p1), sym(p0, p0) + sym(p1, p1)])  # (4,C,4,4)
        K9 = K[:, :, _NE_ROWS, _NE_COLS].reshape(4 * C, 9)
        eps = np.zeros((1, 9))
        eps[0, [0, 3, 5]] = _EPS
        self._K = np.ascontiguousarray(np.concatenate([K9, eps]).T)  # (9, 4C+1)
        self._Prows = np.ascontiguousarray(self.Pn.transpose(1, 0, 2).reshape(3 * C, 4))  # (3C,4): rows, cams
        self._Prows_px = self._Prows.copy()  # the x and y rows times the focal scale: pixel residuals
        self._Prows_px[: 2 * C] *= np.tile(self.s, 2)[:, None]
        self._c2 = np.ascontiguousarray(self.c.T)[:, :, None]  # (2,C,1)
        self._s1 = self.s[:, None]  # (C,1)
        self._s2 = self.s[:, None] ** 2

    def normalised(self, xy_px: np.ndarray) -> np.ndarray:
        """(2, ...) normalised coordinates ``(x - c) / s`` of undistorted pixels ``xy_px`` (C, ..., 2)."""
        xy = np.moveaxis(np.asarray(xy_px, dtype=np.float64), -1, 0)
        sh = (2, self.n_cams) + (1,) * (xy.ndim - 2)
        return (xy - self._c2.reshape(sh)) / self.s.reshape(sh[1:])

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
        return self.solve(self.normalised(xy), np.where(seen, w0, 0.0), seen)

    def solve(self, xyn: np.ndarray, w0: np.ndarray, seen: np.ndarray) -> Triangulated:
        """The robust DLT on prepared input: xyn (2,C,N) normalised coordinates (``normalised``; any
        finite value where unseen), w0 (C,N) confidences (0 where unseen), seen (C,N) bool."""
        V, ok, used = self.solve_raw(xyn, w0, seen)
        nan = np.float64(np.nan)
        return Triangulated(
            xyz_m=np.where(ok[:, None], V[:3].T, nan),
            reproj_err_px=np.where(ok, V[_REPROJ], nan),
            n_views=np.where(ok, V[_NVIEWS], 0).astype(np.int16),
            score=np.where(ok, V[_SCORE], 0.0),
            std_m=np.where(ok, V[_STD], nan),
            used=used & ok[None],
        )

    def solve_raw(
        self, xyn: np.ndarray, w0: np.ndarray, seen: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``solve`` without the masking: V (8+C,N) with rows x, y, z, 1, score, reprojection error,
        std, view count (``_SCORE`` ...; meaningful where ok), then the reprojection error in each camera
        (``_PER_VIEW``; NaN where the view was not used: their mean is the reprojection error row),
        ok (N,) and the views used (C,N)."""
        cfg = self.config
        C, N = w0.shape
        xyn = np.where(seen, xyn, 0.0)  # unseen: finite, so every residual below stays finite
        # feature planes of the normal matrices: (w^2 [x^2+y^2, x, y], w^2, 1) (module doc)
        Fe = np.empty((4 * C + 1, N))
        Fe[-1] = 1.0
        F3, Fw = Fe[: 3 * C].reshape(3, C, N), Fe[3 * C : 4 * C]
        xyr = np.empty((3, C, N))
        np.multiply(xyn, xyn, out=xyr[1:])
        np.add(xyr[1], xyr[2], out=xyr[0])
        xyr[1:] = xyn
        np.multiply(w0, w0, out=Fw)
        np.multiply(xyr, Fw, out=F3)
        V = np.empty((_PER_VIEW + C, N))
        Xh = V[:4]  # homogeneous points
        A = self._K @ Fe
        Xh[:3] = _solve9(A)  # algebraic first guess (3,N)
        Xh[3] = 1.0
        depth = self._Prows[2 * C :] @ Xh  # (C,N)
        pos = depth > 1e-6
        used = seen & pos
        ds = np.where(pos, depth, 1.0)
        thr2 = cfg.max_reproj_px**2
        xy_px = xyn * self._s1  # pixels about the principal point, as the scaled projection rows give
        drop = None
        mx = None  # per point, the largest squared error over the views used (after the last projection)
        for it in range(cfg.max_rejections + 1):
            # reweight by inverse projective depth: rows then measure (normalised) pixel error;
            # after a rejection only the points that lost a view take the new solution
            np.divide(w0, ds, out=Fw)
            Fw *= Fw
            Fw *= used
            np.multiply(xyr, Fw, out=F3)
            A_it = self._K @ Fe
            X = _solve9(A_it)
            if drop is None:
                Xh[:3], A = X, A_it
            else:
                np.copyto(Xh[:3], X, where=drop)
                np.copyto(A, A_it, where=drop)
            proj = (self._Prows_px @ Xh).reshape(3, C, N)  # x, y scaled to pixels about c, depth
            depth = proj[2]
            pos = depth > 1e-6
            if pos.all():
                ds = depth
            else:
                used &= pos
                ds = np.where(pos, depth, 1.0)
            e = proj[:2] / ds
            e -= xy_px
            e *= e
            err2 = e[0] + e[1]  # (C,N) squared pixel errors
            if it == cfg.max_rejections:
                mx = None
                break
            err_m = err2 * used  # unused views 0: never the worst above a positive threshold
            mx = err_m.max(0)
            drop = mx > thr2
            if not drop.any():
                break
            drop &= np.count_nonzero(used, 0) > cfg.min_views
            if not drop.any():
                break
            idx = drop.nonzero()[0]
            used[err_m[:, idx].argmax(0), idx] = False
            mx = None
        ok = self._point_statistics(V, A, used, err2, w0, mx)
        return V, ok, used

    def _point_statistics(
        self, V: np.ndarray, A: np.ndarray, used: np.ndarray, err2: np.ndarray, w0: np.ndarray, mx
    ) -> np.ndarray:
        """Fill V's score, error, spread and view-count rows from the views ``used`` of the last solve
        (normal matrices ``A``, squared errors ``err2``); returns which points pass the checks."""
        cfg = self.config
        C, N = w0.shape
        thr2 = cfg.max_reproj_px**2
        tr = _inv_trace(A)
        # per-point sums over the views used: count, confidence, error, squared confidence,
        # squared error, squared focal scale
        E = np.empty((6, C, N))
        E[0] = used
        np.multiply(E[0], w0, out=E[1])
        np.multiply(err2, E[0], out=E[4])
        np.sqrt(E[4], out=E[2])
        np.multiply(E[1], w0, out=E[3])
        np.multiply(E[0], self._s2, out=E[5])
        tot = E.sum(1)  # (6,N)
        n_views = V[_NVIEWS]
        n_views[:] = tot[0]
        mean = tot[1:] / np.maximum(n_views, 1.0)  # score, reprojection error, w^2, err^2, s^2
        V[_SCORE : _SCORE + 2] = mean[:2]
        np.copyto(V[_PER_VIEW:], E[2])  # per-view pixel errors of the final point
        V[_PER_VIEW:][~used] = np.nan
        # covariance sigma^2 (J^T W J)^-1 from the last solve's normal matrix: its rows are the
        # Jacobian d(normalised pixel)/dX weighted by the confidences; back to pixels with the mean
        # focal scale and mean squared confidence of the views used
        sigma = np.maximum(cfg.noise_px, np.sqrt(mean[3]))
        std = V[_STD]
        np.multiply(sigma, np.sqrt(np.maximum(tr, 0) * mean[2] / np.maximum(mean[4], 1e-12) / 3.0), out=std)
        # (a non-finite point fails here too: its depth or error is NaN, so no view stays used / max is NaN)
        max_ok = (E[4].max(0) if mx is None else mx) <= thr2
        return (n_views >= cfg.min_views) & max_ok & (std <= cfg.max_std_m)


def triangulate_dlt(
    P: np.ndarray, xy_px: np.ndarray, weights: np.ndarray | None = None, min_views: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Plain weighted DLT (no rejection). P: (C,3,4); xy_px: (C,N,2), NaN = unseen; weights: (C,N).

    Returns xyz_m (N,3) (NaN where fewer than ``min_views``) and n_views (N,), the views used (0 where
    the point was not triangulated).

    >>> from triangulate.geometry import project
    >>> K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    >>> P = np.stack([K @ np.hstack([np.eye(3), [[dx], [0], [2]]]) for dx in (0.0, -0.5, 0.5)])
    >>> X = np.array([[0.1, -0.2, 0.3], [0.0, 0.4, -0.1]])
    >>> xy = project(P, X)
    >>> xy[1:, 1] = np.nan  # the second point is seen by the first camera only
    >>> xyz_m, n_views = triangulate_dlt(P, xy)
    >>> np.round(xyz_m, 6) + 0.0, n_views.tolist()
    (array([[ 0.1, -0.2,  0.3],
           [ nan,  nan,  nan]]), [3, 0])
    """
    cfg = DLTConfig(min_views=min_views, min_score=0.0, max_reproj_px=1e9, max_rejections=0, max_std_m=1e9)
    r = Triangulator(P, cfg)(xy_px, weights)
    return r.xyz_m, r.n_views


# Plausible limb lengths (metres) by joint-name pair: generous bounds that still catch a joint
# triangulated from mismatched or flipped views.
LIMB_BOUNDS_M = {
    ("left_shoulder", "left_elbow"): (0.12, 0.50),
    ("right_shoulder", "right_elbow"): (0.12, 0.50),
    ("left_elbow", "left_wrist"): (0.10, 0.45),
    ("right_elbow", "right_wrist"): (0.10, 0.45),
    ("left_hip", "left_knee"): (0.20, 0.65),
    ("right_hip", "right_knee"): (0.20, 0.65),
    ("left_knee", "left_ankle"): (0.20, 0.65),
    ("right_knee", "right_ankle"): (0.20, 0.65),
    ("left_shoulder", "right_shoulder"): (0.15, 0.60),
    ("left_hip", "right_hip"): (0.08, 0.50),
    ("neck", "pelvis"): (0.25, 0.90),
    ("nose", "neck"): (0.03, 0.45),
}
# Hands (the 42 joints of keypoints.skeletons.HANDS): the body's wrist and the hand's own root are one
# point seen by two models (within 10 cm); a palm bone (root to a finger's first joint) 1.5-13 cm, a
# phalanx 0.8-7 cm (adult hands: metacarpals 4-8 cm, phalanges 1.5-5 cm).
for _side in ("left", "right"):
    LIMB_BOUNDS_M[(f"{_side}_wrist", f"{_side}_hand_root")] = (0.0, 0.10)
    for _p, _c in HAND_BONES:
        if _c.startswith(_side):
            LIMB_BOUNDS_M[(_p, _c)] = (0.015, 0.13) if _p.endswith("hand_root") else (0.008, 0.07)


def _pairs(joint_names: tuple[str, ...], bounds: dict):
    idx = {n: i for i, n in enumerate(joint_names)}
    pairs = [
        (idx[a], idx[b], lo * lo, hi * hi) for (a, b), (lo, hi) in bounds.items() if a in idx and b in idx
    ]  # squared bounds
    return tuple(np.asarray(v) for v in zip(*pairs, strict=True)) if pairs else None


@functools.cache
def _limb_pairs(joint_names: tuple[str, ...]):
    return _pairs(joint_names, LIMB_BOUNDS_M)


def limb_check(
    xyz_m: np.ndarray, reproj_err_px: np.ndarray, joint_names: tuple[str, ...], bounds: dict | None = None
) -> np.ndarray:
    """Plausibility of limb lengths. xyz_m: (M,J,3); reproj_err_px: (M,J).

    For each limb outside its bounds the endpoint with the larger reprojection error is marked.
    Returns a (M,J) bool mask of joints to keep.
    """
    pairs = _limb_pairs(tuple(joint_names)) if bounds is None else _pairs(tuple(joint_names), bounds)
    keep = np.ones(xyz_m.shape[:2], bool)
    drop = limb_outliers(np.moveaxis(np.asarray(xyz_m, dtype=np.float64), -1, 0), reproj_err_px, pairs)
    if drop is not None:
        keep[drop] = False
    return keep


def limb_outliers(X: np.ndarray, reproj_err_px: np.ndarray, pairs) -> tuple | None:
    """``limb_check`` on coordinate planes X (3,M,J) (NaN = missing) with the pairs of ``_limb_pairs``:
    the (person, joint) indices to drop, or None when every limb is plausible."""
    if pairs is None:
        return None
    a, b, lo2, hi2 = pairs  # squared bounds
    dv = X[:, :, a] - X[:, :, b]  # (3,M,L)
    dv *= dv
    length2 = dv[0] + dv[1]
    length2 += dv[2]  # (M,L) squared limb lengths
    bad = (length2 < lo2) | (length2 > hi2)  # NaN (a missing endpoint) is neither
    if not bad.any():
        return None
    ea, eb = np.nan_to_num(reproj_err_px[:, a]), np.nan_to_num(reproj_err_px[:, b])
    m, limb = np.nonzero(bad)
    return m, np.where(ea[m, limb] >= eb[m, limb], a[limb], b[limb])
