"""Iterative greedy matching of 2D poses across views (seed sec. 4.2.1, Algorithm 1, eq. 4.1-4.4).

Cameras are visited in a given order. The first camera's 2D poses start the person hypotheses
H; for each further camera i the cost of assigning pose h_{i,k} to hypothesis H_m is the average,
over the poses already in H_m, of the average symmetric epipolar distance over the joints both
poses see (eq. 4.2, 4.3). The assignment is solved as a bipartite matching (eq. 4.4, Hungarian via
``scipy.optimize.linear_sum_assignment``); matched pairs below theta join the hypothesis, every
other pose of camera i starts a new one. Hypotheses with a single pose are dropped at the end.

Eq. 4.3 writes the algebraic residual ``|p_j^T F p_i|``; the text defines it as the distance
between the joint and the epipolar line, which is what we compute (the residual divided by the
norm of the line's normal, i.e. pixels), so theta is in pixels.

Eq. 4.3 for *every* pair of poses of the frame (and with either pose left/right mirrored) is
one batched matrix product over (camera, joint) (:meth:`Matcher.pair_table`); Algorithm 1's loop
then reads, per camera, the costs of its poses against all hypothesis members with one gather
and averages them (eq. 4.2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from roomcap.core.config import config_from_dict
from roomcap.triangulate.geometry import check_shape

_BIG = 1e9
_O01 = np.array([0, 1])[:, None, None]  # S ^ 0 = S, S ^ 1 = 1 - S for S in {0, 1}


@dataclass(frozen=True)
class MatchConfig:
    """Association settings.

    theta_px: a pose joins a hypothesis when its mean symmetric epipolar distance (eq. 4.2) is below.
    camera_order: camera names (or None = the rig's order) in which views are integrated.
    min_score: 2D joints with lower confidence are ignored.
    min_joints: 2D poses with fewer usable joints are ignored.
    min_shared_joints: pairs of poses sharing fewer joints get no epipolar evidence.
    gate: set costs >= theta to "infinite" before the Hungarian step. Algorithm 1 thresholds after
      the assignment, so a pair above theta can take a pose from a valid pair (False = as the seed).
    """

    theta_px: float = 40.0
    camera_order: tuple[str, ...] | None = None
    min_score: float = 0.05
    min_joints: int = 4
    min_shared_joints: int = 3
    gate: bool = True

    def __post_init__(self) -> None:
        if self.theta_px <= 0:
            raise ValueError(f"MatchConfig.theta_px must be positive, got {self.theta_px}.")
        if self.camera_order is not None:
            object.__setattr__(self, "camera_order", tuple(str(c) for c in self.camera_order))

    @classmethod
    def from_dict(cls, d: dict) -> MatchConfig:
        return config_from_dict(cls, d)


def _as_float(F) -> np.ndarray:
    F = np.asarray(F)
    return F if F.dtype in (np.float32, np.float64) else F.astype(np.float64)


def finite_xy(xy: np.ndarray) -> np.ndarray:
    """(...,) True where both coordinates of xy (...,2) are finite (NaN = missing). One add and
    one test instead of ``np.isfinite(xy).all(-1)``'s reduction over a length-2 axis (a sum
    overflows only for coordinates beyond 1e308, which no image has)."""
    return np.isfinite(xy[..., 0] + xy[..., 1])


def _usable(finite: np.ndarray, score: np.ndarray, cfg: MatchConfig) -> np.ndarray:
    """Joints the matching uses (C,P,J): finite coordinates (``finite``), confidence >= min_score, in
    poses with at least min_joints such joints."""
    # NaN scores count as 0 (a NaN never passes ``>=``, so nan_to_num is only needed for min_score <= 0)
    vis = finite & ((score if cfg.min_score > 0 else np.nan_to_num(score)) >= cfg.min_score)
    vis &= (np.count_nonzero(vis, -1) >= cfg.min_joints)[..., None]
    return vis


class Matcher:
    """Algorithm 1 for one rig: per-rig constants (float32 F, camera order, joint permutations) made
    once; ``__call__`` associates one frame (see :func:`match_frame`).

    The pair table. With lines ``L[a,b,j,p] = F[a,b] x[a,p,j]`` scaled to a unit normal (the
    epipolar line in camera b of joint j of pose p in camera a) the summed point-line distances
    ``B[b,a,p,h,q] = sum_j |L[a,b,j,p] . x[b,q,f_h(j)]|`` (f_0 = identity, f_1 = the left/right
    permutation) give eq. 4.3 for every pair of poses, as detected (h = 0) and with the first pose
    mirrored (h = 1): the line of the mirrored pose at joint j is the line of joint f(j), so after
    substituting j -> f(j) its distances to b's points are ``B[b,a,p,1,q]``, and the distances of
    a's mirrored points to b's lines are ``B[a,b,q,1,p]``. So cost_h(a_p, b_q) = (B[b,a,p,h,q] +
    B[a,b,q,h,p]) / n_h(a_p, b_q), with n_h the number of joints both see: one batched product
    over (camera, joint) of (C P x 3) line blocks with (3 x H P) point blocks computes every cost
    of the frame, mirrored ones included.
    Unusable joints get a zero homogeneous vector, so they contribute nothing to any sum.
    """

    def __init__(
        self,
        F: np.ndarray,
        config: MatchConfig | None = None,
        order: np.ndarray | None = None,
        flip: np.ndarray | None = None,
    ):
        self.config = config or MatchConfig()
        F = _as_float(F)
        C = len(F)
        check_shape("F", F, (C, C, 3, 3))
        self.n_cams = C
        # float32 on purpose: numpy's batched matmul of tiny float32 matrices is much faster than float64
        # here, and pixel distances keep ~1e-4 px precision (a float32 F from the caller is used as is)
        self._F32 = np.ascontiguousarray(F.reshape(C, C * 3, 3), dtype=np.float32)
        self.order = (np.arange(C) if order is None else np.asarray(order, dtype=np.int64)).tolist()
        if len(set(self.order)) < len(self.order) or not all(0 <= i < C for i in self.order):
            raise ValueError(f"camera order {self.order}: each camera index (0..{C - 1}) at most once.")
        if flip is not None:
            flip = np.asarray(flip, dtype=np.int64)
            if (flip == np.arange(len(flip))).all():
                flip = None
        self.flip = flip
        # joint index per orientation: (J,H), H = 1 (as detected) or 2 (and mirrored)
        self._jh = None if flip is None else np.stack([np.arange(len(flip)), flip], 1)
        self._cams = np.arange(C)
        self._o01 = np.zeros((1, 1, 1), np.int64) if flip is None else _O01  # o = S ^ _o01: S, 1 - S

    def pair_table(self, xy: np.ndarray, vis: np.ndarray) -> np.ndarray:
        """G (C, P, H, C, P+1) complex: the real part of G[a,p,h,b,q] is the cost of pose p of camera a
        (mirrored if h = 1) against pose q of camera b in pixels (class doc; 0 where fewer than
        ``min_shared_joints`` joints are shared), the imaginary part 1 where the cost is
        valid, else 0. The last column (q = P, index -1) is all zero: hypotheses index it for
        cameras they have no pose in."""
        C, P, J = vis.shape
        jh = self._jh
        Hn = 1 if jh is None else 2
        if jh is not None and len(jh) != J:
            raise ValueError(f"flip has {len(jh)} joints, the poses {J}.")
        xs = np.empty((C, 3, J, P), np.float32)  # homogeneous points, zero where unusable
        xs[:, :2] = np.where(vis[..., None], xy, 0.0).transpose(0, 3, 2, 1)
        xs[:, 2] = vis.transpose(0, 2, 1)
        L = np.matmul(self._F32, xs.reshape(C, 3, J * P)).reshape(C, C, 3, J, P)  # (a,b,k,j,p)
        nrm = np.sqrt(L[:, :, 0] ** 2 + L[:, :, 1] ** 2)
        np.maximum(nrm, 1e-12, out=nrm)
        L /= nrm[:, :, None]
        Lc = np.empty((C, J, C, P, 3), np.float32)  # (b,j,a,p,k): unit-normal lines, batched by (b, j)
        Lc[...] = L.transpose(1, 3, 0, 4, 2)
        # points x[b,q,f_h(j)] (b,j,k,h,q): sum_j |L[a,b,f(j),p].x[b,q,j]| = sum_j |L[a,b,j,p].x[b,q,f(j)]|,
        # so the mirrored poses' costs need no lines of their own
        xq = (xs[:, :, jh] if jh is not None else xs[:, :, :, None]).transpose(0, 2, 1, 3, 4)
        xq = xq.reshape(C, J, 3, Hn * P)
        Lm = Lc.reshape(C, J, C * P, 3)
        if P < 8:  # the same products; numpy/BLAS is faster with the long side first for larger frames
            B = np.matmul(Lm, xq)  # (b,j,(a,p),(h,q))
            np.abs(B, out=B)
            B = B.sum(1).reshape(C, C, P, Hn, P)
        else:
            B = np.matmul(xq.transpose(0, 1, 3, 2), Lm.transpose(0, 1, 3, 2))  # (b,j,(h,q),(a,p))
            np.abs(B, out=B)
            B = B.sum(1).reshape(C, Hn, P, C, P).transpose(0, 3, 4, 1, 2)
        # B[b,a,p,h,q] = sum_j |L[a,b,j,p] . x[b,q,f_h(j)]|; eq. 4.3 both ways, laid out (a,p,h,b,q):
        # B[b,a,p,h,q] (a's pose p, mirrored if h, against b's lines) + B[a,b,q,h,p] (the other way)
        d = B.transpose(1, 2, 3, 0, 4) + B.transpose(0, 4, 3, 1, 2)
        v = vis.astype(np.float64)
        vh = v if jh is None else v[:, :, jh.T]  # (a,p,h,J)
        n = (vh.reshape(C * P * Hn, J) @ v.reshape(C * P, J).T).reshape(C, P, Hn, C, P)
        ok = n >= max(self.config.min_shared_joints, 1)
        # cost + 1j * ok: Algorithm 1's loop then reads both with one gather of plain indices. (The
        # a == b blocks are never read: a camera's poses meet hypotheses before it has joined any.)
        G = np.zeros((C, P, Hn, C, P + 1), np.complex128)
        Gv = G[..., :P]
        np.divide(d, n, out=Gv.real, where=ok)
        Gv.imag = ok
        return G

    def __call__(self, xy_px: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Associate one frame: see :func:`match_frame` (same arguments and result)."""
        xy = np.asarray(xy_px, dtype=np.float64)
        C = self.n_cams
        check_shape("xy_px", xy, (C, None, None, 2))
        score = np.asarray(score, dtype=np.float64)
        check_shape("score", score, xy.shape[:3])
        return self.match(xy, score, finite_xy(xy))

    def match(self, xy: np.ndarray, score: np.ndarray, finite: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``__call__`` on checked input: xy (C,P,J,2) and score (C,P,J) float64, finite (C,P,J) =
        ``finite_xy(xy)``."""
        cfg = self.config
        vis = _usable(finite, score, cfg)
        present = vis.any(-1)  # (C,P)
        G = self.pair_table(xy, vis)
        flip = self.flip is not None
        C = self.n_cams
        n_max = int(np.count_nonzero(present))
        H = np.full((n_max, C), -1, dtype=np.int64)  # hypotheses: pose index per camera, -1 = none
        S = np.zeros((n_max, C), dtype=np.int64)  # 1 = pose mirrored relative to its hypothesis
        m = 0  # hypotheses so far: H[:m]
        theta = cfg.theta_px
        cams, o01 = self._cams, self._o01
        for i in self.order:
            ks = present[i].nonzero()[0]
            K = len(ks)
            if K == 0:
                continue
            if m:
                Hm, Sm = H[:m], S[:m]
                # eq. 4.2: mean over the hypothesis' members (that share joints with the pose) of eq. 4.3,
                # each member in its own orientation (o = S), or the pose mirrored against it (o = 1 - S);
                # H = -1 reads the zero column
                t = G[i][ks[:, None, None, None], Sm ^ o01, cams, Hm].sum(-1)  # (K,o,M) cost + 1j count
                t_ok = t.imag
                phis = np.divide(t.real, t_ok, out=np.full(t.shape, _BIG), where=t_ok > 0)
                if flip:
                    phi = phis[:, 0]
                    # prefer the pose as detected unless mirroring clearly helps
                    mirrored = phis[:, 1] < 0.8 * phi
                    phi = np.where(mirrored, phis[:, 1], phi)
                else:
                    phi = phis[:, 0]
                if cfg.gate:  # pairs above theta cannot join anyway; keep them from displacing valid pairs
                    phi[phi >= theta] = _BIG
                rows, cols = linear_sum_assignment(phi)  # eq. 4.4
                joined = phi[rows, cols] < theta
                rj, cj = rows[joined], cols[joined]
                H[cj, i] = ks[rj]
                if flip:
                    S[cj, i] = mirrored[rj, cj]
                if len(rj) < K:  # the rest start new hypotheses
                    new = np.ones(K, bool)
                    new[rj] = False
                    new = ks[new]
                else:
                    continue
            else:
                new = ks
            H[m : m + len(new), i] = new
            m += len(new)
        H, S = H[:m], S[:m]
        keep = np.count_nonzero(H >= 0, 1) >= 2
        H, S = H[keep], S[keep].astype(bool)
        if flip and S.any():  # a hypothesis started from a mirrored pose: take the majority orientation
            has = H >= 0
            invert = 2 * np.count_nonzero(S, 1) > np.count_nonzero(has, 1)
            S[invert] = ~S[invert]
            S &= has
        return H, S


def match_frame(
    xy_px: np.ndarray,
    score: np.ndarray,
    F: np.ndarray,
    config: MatchConfig | None = None,
    order: np.ndarray | None = None,
    flip: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1 for one frame.

    xy_px: (C,P,J,2) undistorted pixels, NaN = missing (P = most poses in any camera, padded);
    score: (C,P,J); F: (C,C,3,3) with ``x_j^T F[i,j] x_i = 0``; order: camera indices (C',) to visit
    (default 0..C-1); flip: (J,) left/right joint permutation, or None to take every pose as it is.
    Returns the hypotheses as (M,C) int: the pose index in each camera or -1 (every row has at
    least two poses) and (M,C) bool: the pose is mirrored (left/right swapped) relative to the
    hypothesis. The seed notes left/right flips of single views as its main failure (sec. 4.3.5):
    with ``flip`` each pose joins in the orientation with the lower cost (eq. 4.2 against the
    members in their own orientation), and each hypothesis takes its majority orientation.
    A :class:`Matcher` keeps the per-rig constants for repeated frames.
    """
    xy = np.asarray(xy_px, dtype=np.float64)
    check_shape("xy_px", xy, (None, None, None, 2))
    check_shape("F", np.asarray(F), (len(xy), len(xy), 3, 3))
    return Matcher(F, config, order, flip)(xy, score)
