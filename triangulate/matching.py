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

The cost of *all* poses of camera i against *all* poses already placed is computed at once,
vectorised over (cameras seen so far x poses x poses x joints); eq. 4.2's average over the
hypothesis' members is then one matrix product with the membership matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from triangulate.dlt import _reject_unknown
from triangulate.geometry import check_shape

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
        return cls(**_reject_unknown(cls, d))


def _as_float(F) -> np.ndarray:
    F = np.asarray(F)
    return F if F.dtype in (np.float32, np.float64) else F.astype(np.float64)


def _usable(xy: np.ndarray, score: np.ndarray, cfg: MatchConfig) -> np.ndarray:
    # NaN scores count as 0 (a NaN never passes ``>=``, so nan_to_num is only needed for min_score <= 0)
    vis = np.isfinite(xy).all(-1) & ((score if cfg.min_score > 0 else np.nan_to_num(score)) >= cfg.min_score)
    vis &= (vis.sum(-1) >= cfg.min_joints)[..., None]
    return vis


def _homog(xy: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(C,P,J,2) -> homogeneous (C,3,J,P) float32, zero vector where not usable.

    float32 on purpose: numpy's batched matmul of tiny float32 matrices is ~10x faster than float64
    here, and pixel distances keep ~1e-4 px precision."""
    C, P, J = vis.shape
    xs = np.empty((C, 3, J, P), np.float32)
    xs[:, :2] = np.where(vis[..., None], xy, 0.0).transpose(0, 3, 2, 1)
    xs[:, 2] = vis.transpose(0, 2, 1)
    return xs


def _lines(xs: np.ndarray, F: np.ndarray) -> np.ndarray:
    """L[a,b,k,j,p] = (F[a,b] x_{a,p,j})_k: epipolar lines in camera b, scaled to a unit normal."""
    C, _, J, P = xs.shape
    F32 = F.reshape(C, C * 3, 3).astype(np.float32, copy=False)  # a float32 F (from the caller) is used as is
    L = np.matmul(F32, xs.reshape(C, 3, J * P)).reshape(C, C, 3, J, P)
    nrm = np.sqrt(L[:, :, 0] ** 2 + L[:, :, 1] ** 2)
    np.maximum(nrm, 1e-12, out=nrm)
    L /= nrm[:, :, None]
    return L


def _dist(L: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """(a,b,Pa,Pb): sum over joints of |point-line distance| in camera b of b's points to a's lines."""
    d = np.matmul(L.transpose(0, 1, 3, 4, 2), xs.transpose(0, 2, 1, 3)[None])  # (a,b,J,Pa,Pb)
    np.abs(d, out=d)
    return d.sum(2)


def pair_costs(xy: np.ndarray, vis: np.ndarray, F: np.ndarray, min_shared: int = 1,
               flip: np.ndarray | None = None) -> tuple:
    """Mean symmetric epipolar distance (eq. 4.3 averaged over shared joints) between all pose pairs.

    xy (C,P,J,2) undistorted pixels, vis (C,P,J) usable joints, F (C,C,3,3) with x_b^T F[a,b] x_a = 0.
    Returns cost (C,P,C,P) in pixels and ok (C,P,C,P), False where fewer than ``min_shared`` joints
    are shared (or a == b). Unusable joints get a zero homogeneous vector, so they contribute
    nothing to any sum and the whole computation is a handful of batched matrix products.
    With ``flip`` (J,) (the left/right joint permutation) also the cost and ok of the first pose
    mirrored against the second unmirrored (``cross``; else None).
    """
    C, P, J = vis.shape
    if flip is None:
        xs = _homog(xy, vis)
        L = _lines(xs, F)
    else:  # the poses and their mirror images in one pass: (C,3,J,2P)
        vf = vis[:, :, flip]
        xs2 = _homog(np.concatenate([xy, xy[:, :, flip]], 1), np.concatenate([vis, vf], 1))
        L2 = _lines(xs2, F)
        xs, xsf, L = xs2[..., :P], xs2[..., P:], L2[..., :P]
    d_all = _dist(L if flip is None else L2, xs)  # (a,b,P or 2P,P)
    d = d_all[:, :, :P]
    d = (d + d.transpose(1, 0, 3, 2)).astype(np.float64)  # symmetric: in b plus in a (eq. 4.3)
    v = vis.reshape(C * P, J).astype(np.float64)
    n = (v @ v.T).reshape(C, P, C, P)
    cost = d.transpose(0, 2, 1, 3) / np.maximum(n, 1)
    ok = n >= max(min_shared, 1)
    ok[np.arange(C), :, np.arange(C), :] = False
    if flip is None:
        return cost, ok, None, None
    # cost(a'_p, b_q): b's points to the mirrored poses' lines, plus the mirrored points to b's lines
    dx = (d_all[:, :, P:] + _dist(L, xsf).transpose(1, 0, 3, 2)).astype(np.float64)
    nx = (vf.reshape(C * P, J).astype(np.float64) @ v.T).reshape(C, P, C, P)
    cross = dx.transpose(0, 2, 1, 3) / np.maximum(nx, 1)
    okx = nx >= max(min_shared, 1)
    okx[np.arange(C), :, np.arange(C), :] = False
    return cost, ok, cross, okx


def match_frame(xy_px: np.ndarray, score: np.ndarray, F: np.ndarray, config: MatchConfig | None = None,
                order: np.ndarray | None = None, flip: np.ndarray | None = None
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
    """
    cfg = config or MatchConfig()
    xy = np.asarray(xy_px, dtype=np.float64)
    check_shape("xy_px", xy, (None, None, None, 2))
    C, P, J = xy.shape[:3]
    check_shape("score", np.asarray(score), (C, P, J))
    check_shape("F", np.asarray(F), (C, C, 3, 3))
    order = np.arange(C) if order is None else np.asarray(order, dtype=np.int64)
    vis = _usable(xy, np.asarray(score, dtype=np.float64), cfg)
    present = vis.any(-1)  # (C,P)
    if flip is not None:
        flip = np.asarray(flip, dtype=np.int64)
        if (flip == np.arange(J)).all():
            flip = None
    cost_all, ok_all, cross_all, okx_all = pair_costs(xy, vis, _as_float(F),
                                                      cfg.min_shared_joints, flip)
    # G[i][k, q, o, c, h]: q = 0: the cost (0 where not ok), q = 1: ok; o = 0: both poses as
    # detected, o = 1: the first mirrored (= the second mirrored). One gather per camera reads all.
    if flip is None:
        G = np.stack([np.where(ok_all, cost_all, 0.0), ok_all], 2)[:, :, :, None]  # (C,P,2,1,C,P)
    else:
        G = np.empty((C, P, 2, 2, C, P))
        np.copyto(G[:, :, 0, 0], np.where(ok_all, cost_all, 0.0))
        np.copyto(G[:, :, 0, 1], np.where(okx_all, cross_all, 0.0))
        G[:, :, 1, 0], G[:, :, 1, 1] = ok_all, okx_all
    cams = np.arange(C)[None, None, :]  # (1,1,C), with o (o,M,C)
    H = np.full((0, C), -1, dtype=np.int64)  # hypotheses: pose index per camera, -1 = none
    S = np.zeros((0, C), dtype=np.int64)  # 1 = pose mirrored relative to its hypothesis
    theta = cfg.theta_px
    for i in order.tolist():
        ks = present[i].nonzero()[0]
        if len(ks) == 0:
            continue
        new = None
        if len(H):
            # eq. 4.2: mean over the hypothesis' members (that share joints with the pose) of eq. 4.3,
            # each member taken in its own orientation: pose as is vs member mirrored = cross cost
            valid = H >= 0
            # o = S: each member in its own orientation; o = 1 - S: the pose mirrored against it
            o = S[None] ^ _O01 if flip is not None else np.zeros((1,) + S.shape, np.int64)  # (o,M,C): S, 1-S
            t = (G[i][ks][:, :, o, cams, np.maximum(H, 0)] * valid).sum(-1)  # (K,q,o,M)
            phis = np.where(t[:, 1] > 0, t[:, 0] / np.maximum(t[:, 1], 1), _BIG)  # (K,o,M)
            phi = phis[:, 0]
            if flip is not None:
                phi1 = phis[:, 1]
                mirrored = phi1 < 0.8 * phi  # prefer the pose as detected unless mirroring clearly helps
                phi = np.where(mirrored, phi1, phi)
            else:
                mirrored = np.zeros(phi.shape, bool)
            if cfg.gate:  # pairs above theta cannot join anyway; keep them from displacing valid pairs
                phi[phi >= theta] = _BIG
            rows, cols = linear_sum_assignment(phi)  # eq. 4.4
            joined = phi[rows, cols] < theta
            rj, cj = rows[joined], cols[joined]
            H[cj, i] = ks[rj]
            S[cj, i] = mirrored[rj, cj]
            if len(rj) < len(ks):
                new = np.ones(len(ks), bool)
                new[rj] = False
                new = ks[new]
        else:
            new = ks
        if new is not None:
            Hn = np.full((len(new), C), -1, dtype=np.int64)
            Hn[:, i] = new
            H = np.concatenate([H, Hn], 0)
            S = np.concatenate([S, np.zeros(Hn.shape, np.int64)], 0)
    keep = (H >= 0).sum(1) >= 2
    H, S = H[keep], S[keep].astype(bool)
    # a hypothesis started from a mirrored pose: take the majority orientation
    invert = 2 * (S & (H >= 0)).sum(1) > (H >= 0).sum(1)
    S[invert] = ~S[invert]
    S &= H >= 0
    return H, S
