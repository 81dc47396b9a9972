"""Forecasting metrics (numpy): MPJPE, NDMS, APD, ADE, FDE, NPSS, SSCP.

Conventions follow the code behind the seed's numbers (DESIGN.md errata):
MPJPE averages over joints (Tanke eq. 3.25 prints a sum); NPSS compares *cumulative* normalised
power spectra (eq. 3.26-3.29 as in Gopalakrishnan et al.'s code); APD is DLow's pdist (mean pairwise
L2 distance between flattened samples); ADE/FDE are DLow's best-of-S; the SSCP distance is the square
root of the Jensen-Shannon divergence (eq. 7.15, base-2 logs so it lies in [0, 1]).

Shapes: S samples, T frames, J joints. Sequences are ``(T,J,3)`` metres; sample sets ``(S,T,J,3)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from forecast.data import hip_indices, norm_frame, normalize

# Joints used for the nearest-neighbour search and the score (Tanke sec. 6.3.2).
NDMS_JOINTS = (
    "left_wrist",
    "right_wrist",
    "left_elbow",
    "right_elbow",
    "left_shoulder",
    "right_shoulder",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)


def _check(name: str, a: np.ndarray, ndim: int, last: tuple[int, ...] = (3,)) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim != ndim or a.shape[-len(last) :] != last:
        raise ValueError(f"{name}: expected {ndim} dims ending in {last}, got shape {a.shape}")
    return a


# ----------------------------------------------------------------------------- MPJPE (eq. 3.25)


def mpjpe(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-frame mean per-joint position error. pred, gt: (...,T,J,3); mask (...,T,J) -> (T,) metres,
    averaged over joints and leading dims (masked entries excluded; NaN where a frame has none)."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(f"mpjpe: pred {pred.shape} and gt {gt.shape} must match and end in 3")
    err = np.linalg.norm(pred - gt, axis=-1)
    m = np.isfinite(err) if mask is None else (np.asarray(mask, bool) & np.isfinite(err))
    err = np.where(m, err, 0.0)
    axes = tuple(i for i in range(err.ndim) if i != err.ndim - 2)
    with np.errstate(invalid="ignore"):
        return err.sum(axes) / m.sum(axes)


# ----------------------------------------------------------------------------- APD / ADE / FDE (DLow)


def apd(samples: np.ndarray) -> float:
    """DLow's average pairwise distance: mean over sample pairs of ||a - b|| of flattened sequences.
    samples (S,T,J,3) (or (S,D)). 0 for S < 2."""
    s = np.asarray(samples, np.float64).reshape(len(samples), -1)
    S = len(s)
    if S < 2:
        return 0.0
    d = np.linalg.norm(s[:, None] - s[None], axis=-1)
    return float(d[np.triu_indices(S, 1)].mean())


def ade(samples: np.ndarray, gt: np.ndarray) -> float:
    """Best-of-S average displacement: min_s mean_t ||x_t - y_t|| over flattened poses (DLow)."""
    s = np.asarray(samples, np.float64).reshape(len(samples), len(gt), -1)
    g = np.asarray(gt, np.float64).reshape(1, len(gt), -1)
    return float(np.linalg.norm(s - g, axis=-1).mean(-1).min())


def fde(samples: np.ndarray, gt: np.ndarray) -> float:
    """Best-of-S final displacement: min_s ||x_T - y_T|| over flattened poses (DLow)."""
    s = np.asarray(samples, np.float64).reshape(len(samples), len(gt), -1)
    g = np.asarray(gt, np.float64).reshape(1, len(gt), -1)
    return float(np.linalg.norm(s[:, -1] - g[:, -1], axis=-1).min())


# ----------------------------------------------------------------------------- NPSS (eq. 3.26-3.29)


def npss(pred: np.ndarray, gt: np.ndarray) -> float:
    """Normalised power spectrum similarity (lower is better). pred, gt: (N,T,D) (or (N,T,J,3))."""
    p = np.asarray(pred, np.float64).reshape(len(pred), pred.shape[1], -1)
    g = np.asarray(gt, np.float64).reshape(len(gt), gt.shape[1], -1)
    if p.shape != g.shape:
        raise ValueError(f"npss: shapes differ {p.shape} vs {g.shape}")
    gp = np.abs(np.fft.fft(g, axis=1)) ** 2
    pp = np.abs(np.fft.fft(p, axis=1)) ** 2
    gtot, ptot = gp.sum(1, keepdims=True), pp.sum(1, keepdims=True)
    gcdf = np.cumsum(gp / np.maximum(gtot, 1e-12), axis=1)
    pcdf = np.cumsum(pp / np.maximum(ptot, 1e-12), axis=1)
    emd = np.abs(pcdf - gcdf).sum(1)  # (N,D) L1 between cumulative spectra (the code's EMD)
    w = gtot[:, 0]
    return float((emd * w).sum() / max(w.sum(), 1e-12))


# ----------------------------------------------------------------------------- NDMS (eq. 6.9-6.12)


def ndms_pair(x: np.ndarray, y: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Eq. 6.11/6.12 for motion words x, y (...,κ,J,3) -> (...,) in [0, 1]."""
    vx, vy = np.diff(x, axis=-3), np.diff(y, axis=-3)
    nx, ny = np.linalg.norm(vx, axis=-1), np.linalg.norm(vy, axis=-1)
    cos = (vx * vy).sum(-1) / (nx * ny + eps)
    mag = np.minimum(nx, ny) / (np.maximum(nx, ny) + eps)
    return (0.5 * (1 + cos) * mag).mean((-1, -2))


def motion_words(seq: np.ndarray, kappa: int, lhip: int, rhip: int) -> np.ndarray:
    """All overlapping words of κ frames of seq (...,T,J,3) -> (...,T-κ+1,κ,J,3), each normalised
    (eq. 3.8) at its own first frame so search and score ignore where and which way the person stands."""
    T = seq.shape[-3]
    idx = np.arange(T - kappa + 1)[:, None] + np.arange(kappa)[None]
    w = seq[..., idx, :, :]
    R, root = norm_frame(w[..., 0, :, :], lhip, rhip)
    return normalize(w, R, root)


class NDMSScorer:
    """Motion-word database D of real motion (sec. 6.3) and the score f_sim (eq. 6.9).

    database: list of real sequences (T_i,J,3) of the same kind (e.g. held-out test clips);
    ``groups`` labels each (e.g. its clip) so a query can exclude its own clip from D.
    """

    def __init__(
        self,
        database: list[np.ndarray],
        joint_names: tuple[str, ...],
        kappa: int = 8,
        groups: list[int] | None = None,
        max_words: int = 20000,
        seed: int = 0,
    ):
        self.kappa = kappa
        names = list(joint_names)
        self.lhip, self.rhip = hip_indices(names)
        self.jsel = np.array([names.index(n) for n in NDMS_JOINTS if n in names])
        words, gid = [], []
        for i, seq in enumerate(database):
            seq = np.asarray(seq, np.float32)
            if len(seq) < kappa or not np.isfinite(seq).all():
                continue
            w = motion_words(seq, kappa, self.lhip, self.rhip)[:, :, self.jsel]
            words.append(w)
            gid.append(np.full(len(w), i if groups is None else groups[i]))
        if not words:
            raise ValueError(
                f"NDMS database is empty: need complete real sequences of at least κ={kappa} frames"
            )
        W, G = np.concatenate(words), np.concatenate(gid)
        if len(W) > max_words:
            keep = np.sort(np.random.default_rng(seed).choice(len(W), max_words, replace=False))
            W, G = W[keep], G[keep]
        self.words = W.astype(np.float32)
        self.flat = self.words.reshape(len(W), -1)
        self.sq = (self.flat**2).sum(1)
        self.groups = G

    def word_scores(self, seq: np.ndarray, exclude_group: int | None = None) -> np.ndarray:
        """g (eq. 6.10) for every motion word of seq (...,T,J,3) -> (...,T-κ+1)."""
        w = motion_words(np.asarray(seq, np.float32), self.kappa, self.lhip, self.rhip)[..., self.jsel, :]
        lead = w.shape[:-3]
        q = w.reshape(-1, w.shape[-3] * w.shape[-2] * 3)
        out = np.empty(len(q))
        bad = None if exclude_group is None else (self.groups == exclude_group)
        for a in range(0, len(q), 2048):
            qq = q[a : a + 2048]
            d = (qq**2).sum(1)[:, None] - 2 * qq @ self.flat.T + self.sq[None]
            if bad is not None and bad.any():
                d[:, bad] = np.inf
            nn = np.argmin(d, 1)
            out[a : a + 2048] = ndms_pair(w.reshape(-1, *w.shape[-3:])[a : a + 2048], self.words[nn])
        return out.reshape(lead)

    def score_forecast(
        self, obs_tail: np.ndarray, samples: np.ndarray, exclude_group: int | None = None
    ) -> np.ndarray:
        """Per-forecast-frame NDMS (eq. 6.9 before averaging over frames): obs_tail (≥κ-1,J,3) the last
        observed frames, samples (S,H,J,3) -> (H,), mean over samples; entry τ scores the word ending at
        forecast frame τ (so the first words include observed frames, as the seed does)."""
        tail = np.asarray(obs_tail)[-(self.kappa - 1) :]
        S = len(samples)
        seqs = np.concatenate([np.broadcast_to(tail, (S, *tail.shape)), samples], 1)
        return self.word_scores(seqs, exclude_group).mean(0)


def ndms(
    scorer: NDMSScorer, obs_tail: np.ndarray, samples: np.ndarray, exclude_group: int | None = None
) -> float:
    """f_sim (eq. 6.9): mean over samples and forecast words."""
    return float(scorer.score_forecast(obs_tail, samples, exclude_group).mean())


# ----------------------------------------------------------------------------- SSCP (sec. 7.3)


def facing_direction(pose: np.ndarray, lhip: int, rhip: int) -> np.ndarray:
    """Unit forward direction (xy) of poses (...,J,3): the hip vector (left->right) turned +90° about z
    (someone facing +y, z up, has the right hip towards +x)."""
    d = pose[..., rhip, :2] - pose[..., lhip, :2]
    f = np.stack([-d[..., 1], d[..., 0]], -1)  # rotate hip vector +90° about z: left->right hip x=1 => y=1
    return f / (np.linalg.norm(f, axis=-1, keepdims=True) + 1e-9)


def default_social_state(
    X: np.ndarray,
    joint_names: tuple[str, ...],
    near_m: float = 2.0,
    facing_deg: float = 45.0,
    present: np.ndarray | None = None,
) -> np.ndarray:
    """Default social signal function s (eq. 7.11) from tracks: X (T,P,J,3) -> (T,) states in [0, 18).

    Per frame: whether any two people are within ``near_m`` (roots), the number of mutually facing
    close pairs (0,1,2+) and the number of one-sided facing close pairs (0,1,2+); 'facing' = the other's
    root within ``facing_deg`` of one's forward direction.
    """
    lh, rh = hip_indices(joint_names)
    X = np.asarray(X, np.float64)
    T, P = X.shape[:2]
    pres = np.ones((T, P), bool) if present is None else np.asarray(present, bool)
    root = 0.5 * (X[..., lh, :2] + X[..., rh, :2])
    fwd = facing_direction(X, lh, rh)
    d = root[:, None] - root[:, :, None]  # (T,i,j) vector from i to j
    dist = np.linalg.norm(d, axis=-1)
    cosang = (fwd[:, :, None] * d).sum(-1) / (dist + 1e-9)
    valid = pres[:, :, None] & pres[:, None] & ~np.eye(P, dtype=bool)[None] & np.isfinite(dist)
    near = valid & (dist < near_m)
    faces = near & (cosang > np.cos(np.radians(facing_deg)))
    iu = np.triu_indices(P, 1)
    any_near = near[:, iu[0], iu[1]].any(-1)
    mutual = (faces & faces.transpose(0, 2, 1))[:, iu[0], iu[1]].sum(-1)
    one = (faces ^ faces.transpose(0, 2, 1))[:, iu[0], iu[1]].sum(-1)
    return (any_near.astype(int) * 9 + np.minimum(mutual, 2) * 3 + np.minimum(one, 2)).astype(np.int64)


N_DEFAULT_STATES = 18


def state_transition_matrix(states: np.ndarray, n_states: int) -> np.ndarray:
    """stm (eq. 7.12): counts of consecutive state pairs (m, m') of states (T,) -> (m,m)."""
    s = np.asarray(states, np.int64)
    M = np.zeros((n_states, n_states))
    if len(s) > 1:
        np.add.at(M, (s[:-1], s[1:]), 1.0)
    return M


def sscp_distribution(
    scenes: list[np.ndarray], state_fn: Callable[[np.ndarray], np.ndarray], n_states: int
) -> np.ndarray:
    """p_sscp (eq. 7.12) over a set of scenes (each (T,P,J,3))."""
    M = sum(state_transition_matrix(state_fn(X), n_states) for X in scenes)
    total = M.sum()
    return M / total if total > 0 else M


def js_distance(p: np.ndarray, q: np.ndarray) -> float:
    """Eq. 7.15: sqrt of the Jensen-Shannon divergence (base 2, in [0, 1])."""
    p, q = np.asarray(p, np.float64).ravel(), np.asarray(q, np.float64).ravel()
    p, q = p / p.sum(), q / q.sum()
    m = 0.5 * (p + q)

    def kl(a, b):
        nz = a > 0
        return float((a[nz] * np.log2(a[nz] / b[nz])).sum())

    return float(np.sqrt(max(0.5 * (kl(p, m) + kl(q, m)), 0.0)))


@dataclass(frozen=True)
class SSCP:
    """The Symbolic Social Cues Protocol with a pluggable social-state function s: (T,P,J,3) -> (T,) ints."""

    state_fn: Callable[[np.ndarray], np.ndarray]
    n_states: int

    def distance(self, real: list[np.ndarray], generated: list[np.ndarray]) -> float:
        """D_JSD (eq. 7.14) between the state-transition distributions of real and generated scenes."""
        return js_distance(
            sscp_distribution(real, self.state_fn, self.n_states),
            sscp_distribution(generated, self.state_fn, self.n_states),
        )
