"""Forecasting metrics (numpy): MPJPE, NDMS, APD, ADE, FDE, NPSS, SSCP.

Conventions follow the code behind the seed's numbers (CONTRACTS.md, where text and code differ):
MPJPE averages over joints (Tanke eq. 3.25 prints a sum); NPSS compares *cumulative* normalised
power spectra of the real part of the DFT (eq. 3.26-3.29 as Gopalakrishnan et al.'s reference code computes
it) and is applied to root-centred poses by the evaluation (the reference code works on joint angles, which
no translation changes); APD is DLow's pdist (mean pairwise L2 distance between flattened samples);
ADE/FDE are DLow's best-of-S and MMADE/MMFDE DLow's multi-modal versions (eq. 3.31-3.33), all on
root-centred poses in the evaluation; NDMS (eq. 6.11/6.12) clamps the velocity norms at eps as the seed's
reference code (jutanke/ndms) does, so a word scores exactly 1 against itself, and forms its motion words from
root-centred poses with the heading kept (``motion_words``, Tables 6.3/6.8); the SSCP distance is the
square root of the Jensen-Shannon divergence (eq. 7.15, base-2 logs so it lies in [0, 1]).

Shapes: S samples, T frames, J joints. Sequences are ``(T,J,3)`` metres; sample sets ``(S,T,J,3)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from roomcap.forecast.lab.data import hip_indices, norm_frame, normalize

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


def closest_sequence_error(per: np.ndarray) -> np.ndarray:
    """per (B,S,T) error of sample s of window b at frame t (NaN: not known) -> (B,T): at frame t the error of
    the sample whose mean error over frames 1..t is lowest, the sample ADE would choose for a sequence that
    ends at t (Tanke Table 6.8, DLow's protocol): one sample for the whole sequence, not the best of each
    frame."""
    per = np.asarray(per, np.float64)
    ok = np.isfinite(per)
    n = np.cumsum(ok, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        prefix = np.where(n > 0, np.cumsum(np.where(ok, per, 0.0), -1) / np.maximum(n, 1), np.inf)
    pick = np.argmin(prefix, 1)  # (B,T)
    best = np.take_along_axis(per, pick[:, None], 1)[:, 0]
    return np.where(np.isfinite(best), best, np.nan)


def mpjpe_best_of_k(samples: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Best-of-k MPJPE per frame, the sample chosen as ADE chooses it (:func:`closest_sequence_error`):
    samples (B,S,T,J,3), gt (B,T,J,3), mask (B,T,J) -> (T,) metres, averaged over windows (NaN where a frame
    has no valid joint)."""
    y, g = np.asarray(samples, np.float64), np.asarray(gt, np.float64)
    if y.ndim != 5 or g.shape != y.shape[:1] + y.shape[2:]:
        raise ValueError(f"mpjpe_best_of_k: samples {y.shape} must be (B,S,T,J,3) and gt {g.shape} (B,T,J,3)")
    err = np.linalg.norm(y - g[:, None], axis=-1)  # (B,S,T,J)
    m = np.isfinite(err) if mask is None else (np.asarray(mask, bool)[:, None] & np.isfinite(err))
    with np.errstate(invalid="ignore", divide="ignore"):
        per = np.where(m, err, 0.0).sum(-1) / m.sum(-1)  # (B,S,T), NaN where a frame has no valid joint
        best = closest_sequence_error(per)
        return np.nanmean(best, 0) if np.isfinite(best).any() else np.full(best.shape[1], np.nan)


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


def root_centred(seq: np.ndarray, lhip: int, rhip: int) -> np.ndarray:
    """Poses relative to their own root (mid-hips) in every frame: (...,J,3) -> (...,J,3). What DLow's
    APD/ADE/FDE/MMADE/MMFDE are computed on (its H3.6M poses are root-relative); no translation changes it."""
    x = np.asarray(seq, np.float64)
    return x - 0.5 * (x[..., lhip : lhip + 1, :] + x[..., rhip : rhip + 1, :])


def root_trajectory(seq: np.ndarray, lhip: int, rhip: int) -> np.ndarray:
    """The root (mid-hips) of poses (...,J,3) -> (...,1,3), for the root trajectory's own ADE/FDE."""
    x = np.asarray(seq, np.float64)
    return 0.5 * (x[..., lhip : lhip + 1, :] + x[..., rhip : rhip + 1, :])


def multimodal_gt(last_obs: np.ndarray, futures: np.ndarray, threshold: float = 0.5) -> list[np.ndarray]:
    """DLow's multi-modal ground truth: for window i, the futures of every window whose last observed
    (root-centred, flattened) pose lies within ``threshold`` of i's (i's own future included).
    last_obs (N,J,3), futures (N,H,J,3) -> N arrays (M_i,H,J,3)."""
    a = np.asarray(last_obs, np.float64).reshape(len(last_obs), -1)
    d = np.sqrt(np.maximum((a**2).sum(1)[:, None] - 2 * a @ a.T + (a**2).sum(1)[None], 0.0))
    return [futures[np.flatnonzero((d[i] < threshold) | (np.arange(len(a)) == i))] for i in range(len(a))]


def mmade(samples: np.ndarray, gt_multi: np.ndarray) -> float:
    """DLow's MMADE: mean over the multi-modal ground truths (M,T,J,3) of best-of-S ADE."""
    return float(np.mean([ade(samples, g) for g in gt_multi]))


def mmfde(samples: np.ndarray, gt_multi: np.ndarray) -> float:
    """DLow's MMFDE: mean over the multi-modal ground truths (M,T,J,3) of best-of-S FDE."""
    return float(np.mean([fde(samples, g) for g in gt_multi]))


# ----------------------------------------------------------------------------- NPSS (eq. 3.26-3.29)


def npss(pred: np.ndarray, gt: np.ndarray) -> float:
    """Normalised power spectrum similarity (lower is better). pred, gt: (N,T,D) (or (N,T,J,3)).

    As the reference code (Gopalakrishnan et al., used by the seed, Table 6.1): power = the square of the
    *real part* of the DFT coefficients per feature, normalised per feature, cumulated over frequency, L1
    between the cumulative spectra, averaged with the ground truth's total power as weights. Pass
    root-centred poses (``root_centred``) so that a translation of the data changes nothing."""
    p = np.asarray(pred, np.float64).reshape(len(pred), pred.shape[1], -1)
    g = np.asarray(gt, np.float64).reshape(len(gt), gt.shape[1], -1)
    if p.shape != g.shape:
        raise ValueError(f"npss: shapes differ {p.shape} vs {g.shape}")
    gp = np.real(np.fft.fft(g, axis=1)) ** 2
    pp = np.real(np.fft.fft(p, axis=1)) ** 2
    gtot, ptot = gp.sum(1, keepdims=True), pp.sum(1, keepdims=True)
    gcdf = np.cumsum(gp / np.maximum(gtot, 1e-12), axis=1)
    pcdf = np.cumsum(pp / np.maximum(ptot, 1e-12), axis=1)
    emd = np.abs(pcdf - gcdf).sum(1)  # (N,D) L1 between cumulative spectra (the code's EMD)
    w = gtot[:, 0]
    return float((emd * w).sum() / max(w.sum(), 1e-12))


# ----------------------------------------------------------------------------- NDMS (eq. 6.9-6.12)


def ndms_pair(x: np.ndarray, y: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """Eq. 6.11/6.12 for motion words x, y (...,κ,J,3) -> (...,) in [0, 1]. Velocity norms are clamped at
    eps as in the seed's reference code (jutanke/ndms), so identical moving words score exactly 1 and a
    still joint against a moving one 0."""
    vx, vy = np.diff(x, axis=-3), np.diff(y, axis=-3)
    nx = np.maximum(np.linalg.norm(vx, axis=-1), eps)
    ny = np.maximum(np.linalg.norm(vy, axis=-1), eps)
    cos = (vx * vy).sum(-1) / (nx * ny)
    mag = np.minimum(nx, ny) / np.maximum(nx, ny)
    return (0.5 * (1 + cos) * mag).mean((-1, -2))


def _words(seq: np.ndarray, kappa: int) -> np.ndarray:
    """All overlapping windows of κ frames of seq (...,T,J,3) -> (...,T-κ+1,κ,J,3)."""
    T = seq.shape[-3]
    idx = np.arange(T - kappa + 1)[:, None] + np.arange(kappa)[None]
    return seq[..., idx, :, :]


def motion_words(seq: np.ndarray, kappa: int, lhip: int, rhip: int) -> np.ndarray:
    """The seed's motion words: all overlapping words of κ frames of seq (...,T,J,3) -> (...,T-κ+1,κ,J,3),
    every frame's pose minus its own root (mid-hips) at that frame, heading as in the data ("3D skeletons
    centered at the origin but with global rotation", Tables 6.3/6.8). The root's own motion is not in the
    word (it is measured apart, as root ADE/FDE), so a rigidly translated still pose moves no joint."""
    return _words(root_centred(seq, lhip, rhip), kappa)


def motion_words_first_frame(seq: np.ndarray, kappa: int, lhip: int, rhip: int) -> np.ndarray:
    """Words normalised (eq. 3.8) at their own first frame only: root and heading of frame 1 removed from
    all κ frames, so the root's motion inside the word still counts (``ndms_word_first_frame``)."""
    w = _words(seq, kappa)
    R, root = norm_frame(w[..., 0, :, :], lhip, rhip)
    return normalize(w, R, root)


# How a motion word is formed before the search and the score: the seed's (every frame root-centred, heading
# kept) and the variant normalised at the word's first frame.
WORD_FORMS: dict[str, Callable[[np.ndarray, int, int, int], np.ndarray]] = {
    "root_centred": motion_words,
    "word_first_frame": motion_words_first_frame,
}


MIN_GROUP_WORDS = (
    50  # an activity group of the database with fewer words than this is an error (2 s at 25 Hz)
)


class NDMSScorer:
    """Motion-word database D of real motion (sec. 6.3, 6.3.2) and the score f_sim (eq. 6.9).

    database: real sequences (T_i,J,3) of held-out motion. ``activities`` labels each sequence with its
    activity: a query is scored against the words of its own activity only ("all *basketball* test
    sequences for evaluating *basketball*", sec. 6.3.2); None puts every sequence in one group.
    ``groups`` labels each sequence with its clip, so that the stricter leave-clip-out variant can drop the
    query's own clip from D (the seed keeps it: g is 1 when D holds the exact word). Every activity needs at
    least ``min_words`` words (ValueError naming the group otherwise). ``max_words`` (None: all) subsamples
    each activity's words. ``word_form`` (``WORD_FORMS``): "root_centred" (the seed's, default) or
    "word_first_frame"; the nearest neighbour is the exact Euclidean one on the flattened words of the
    selected joints (the reference code's Annoy index is approximate).
    """

    def __init__(
        self,
        database: list[np.ndarray],
        joint_names: tuple[str, ...],
        kappa: int = 8,
        groups: list[int] | None = None,
        max_words: int | None = None,
        seed: int = 0,
        activities: list[str] | None = None,
        min_words: int = MIN_GROUP_WORDS,
        word_form: str = "root_centred",
    ):
        if word_form not in WORD_FORMS:
            raise ValueError(f"unknown NDMS word form '{word_form}'; choose from {', '.join(WORD_FORMS)}")
        self.kappa = kappa
        self.word_form = word_form
        self._form = WORD_FORMS[word_form]
        names = list(joint_names)
        self.lhip, self.rhip = hip_indices(names)
        self.jsel = np.array([names.index(n) for n in NDMS_JOINTS if n in names])
        words, gid, act = [], [], []
        for i, seq in enumerate(database):
            seq = np.asarray(seq, np.float32)
            if len(seq) < kappa or not np.isfinite(seq).all():
                continue
            w = self._form(seq.astype(np.float64), kappa, self.lhip, self.rhip)[:, :, self.jsel]
            words.append(w)
            gid.append(np.full(len(w), i if groups is None else groups[i]))
            act.append(np.full(len(w), "all" if activities is None else str(activities[i]), dtype=object))
        if not words:
            raise ValueError(
                f"NDMS database is empty: need complete real sequences of at least κ={kappa} frames"
            )
        W, G, A = np.concatenate(words), np.concatenate(gid), np.concatenate(act)
        wanted = sorted(set(A)) if activities is None else sorted({str(a) for a in activities})
        keep = []
        rng = np.random.default_rng(seed)
        for a in wanted:
            idx = np.flatnonzero(A == a)
            if len(idx) < min_words:
                raise ValueError(
                    f"NDMS database group '{a}' has {len(idx)} motion words (κ={kappa}), fewer than "
                    f"{min_words}: "
                    "add more real sequences of that activity, merge it with a related activity, or lower "
                    "min_words"
                )
            if max_words is not None and len(idx) > max_words:
                idx = np.sort(rng.choice(idx, max_words, replace=False))
            keep.append(idx)
        keep = np.concatenate(keep)
        W, G, A = W[keep], G[keep], A[keep]
        self.words = W.astype(np.float64)
        self.flat = self.words.reshape(len(W), -1)
        self.sq = (self.flat**2).sum(1)
        self.groups = G
        self.activity_of_word = A
        self.activities = tuple(wanted)

    def _candidates(self, activity: str | None, exclude_group: int | None) -> np.ndarray | None:
        ok = None
        if activity is not None:
            if activity not in self.activities:
                raise ValueError(f"activity '{activity}' is not in the NDMS database (has {self.activities})")
            ok = self.activity_of_word == activity
        if exclude_group is not None:
            ok = (self.groups != exclude_group) if ok is None else (ok & (self.groups != exclude_group))
        return ok

    def word_scores(
        self, seq: np.ndarray, exclude_group: int | None = None, activity: str | None = None
    ) -> np.ndarray:
        """g (eq. 6.10) for every motion word of seq (...,T,J,3) -> (...,T-κ+1); NaN where no word of the
        activity is left after excluding ``exclude_group``."""
        # float32 first, as the database (and both sides in the reference code): the query's exact word in D
        # is then at distance 0, not at a float32 rounding away from periodic copies of itself
        seq = np.asarray(np.asarray(seq, np.float32), np.float64)
        w = self._form(seq, self.kappa, self.lhip, self.rhip)[..., self.jsel, :]
        lead = w.shape[:-3]
        q = w.reshape(-1, w.shape[-3] * w.shape[-2] * 3)
        ok = self._candidates(activity, exclude_group)
        if ok is not None and not ok.any():
            return np.full(lead, np.nan)
        flat, sq, words = (
            (self.flat, self.sq, self.words) if ok is None else (self.flat[ok], self.sq[ok], self.words[ok])
        )
        out = np.empty(len(q))
        for a in range(0, len(q), 2048):
            qq = q[a : a + 2048]
            d = (qq**2).sum(1)[:, None] - 2 * qq @ flat.T + sq[None]
            nn = np.argmin(d, 1)
            out[a : a + 2048] = ndms_pair(w.reshape(-1, *w.shape[-3:])[a : a + 2048], words[nn])
        return out.reshape(lead)

    def score_forecast(
        self,
        obs_tail: np.ndarray,
        samples: np.ndarray,
        exclude_group: int | None = None,
        activity: str | None = None,
    ) -> np.ndarray:
        """Per-forecast-frame NDMS (eq. 6.9 before averaging over frames): obs_tail (≥κ-1,J,3) the last
        observed frames, samples (S,H,J,3) -> (H,), mean over samples; entry τ scores the word ending at
        forecast frame τ (so the first words include observed frames, as the seed does)."""
        tail = np.asarray(obs_tail)[-(self.kappa - 1) :]
        S = len(samples)
        seqs = np.concatenate([np.broadcast_to(tail, (S, *tail.shape)), samples], 1)
        return self.word_scores(seqs, exclude_group, activity).mean(0)


def ndms(
    scorer: NDMSScorer,
    obs_tail: np.ndarray,
    samples: np.ndarray,
    exclude_group: int | None = None,
    activity: str | None = None,
) -> float:
    """f_sim (eq. 6.9): mean over samples and forecast words."""
    return float(scorer.score_forecast(obs_tail, samples, exclude_group, activity).mean())


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
