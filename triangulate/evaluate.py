"""Evaluation reusable by every 3D stage: PCP, MPJPE, MOTA (CLEAR MOT) and IDF1.

Shapes: ground truth ``gt (T,G,J,3)`` (NaN = actor absent or joint unknown), predictions
``pred (T,K,J,3)``; both in the same skeleton (body19) and metres.

PCP follows the seed (sec. 4.3) and the Shelf/Campus protocol: per frame and actor the predicted
pose closest to the actor (mean distance over shared joints) is scored; a limb (upper/lower arm
and leg, left and right) is correct when the mean of its two endpoint errors is at most
``alpha`` (0.5) times the true limb length; a missing limb counts as wrong. Reported per actor
and limb type, per actor, as the actor average ("aAvg") and as the frame-weighted average over
all actor-frames ("gAvg").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from roomcap.keypoints.skeletons import CANONICAL, Skeleton, get_skeleton


def _present(X: np.ndarray) -> np.ndarray:
    return np.isfinite(X).all(-1).any(-1)


def mean_joint_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A (G,J,3), B (K,J,3) -> (G,K) mean distance over joints both have (inf if none)."""
    d = np.linalg.norm(A[:, None] - B[None], axis=-1)  # (G,K,J) NaN where either missing
    ok = np.isfinite(d)
    n = ok.sum(-1)
    return np.where(n > 0, np.where(ok, d, 0).sum(-1) / np.maximum(n, 1), np.inf)


@dataclass
class PCPResult:
    per_actor_limb: dict[str, np.ndarray]  # limb type -> (G,) fraction correct
    per_actor: np.ndarray  # (G,)
    actor_average: float  # aAvg
    frame_weighted: float  # gAvg
    n_frames: np.ndarray  # (G,) actor-frames scored

    def table(self) -> str:
        G = len(self.per_actor)
        lines = ["limb        " + " ".join(f"actor{g + 1:>3}" for g in range(G))]
        for k, v in self.per_actor_limb.items():
            lines.append(f"{k:<12}" + " ".join(f"{x:8.3f}" for x in v))
        lines.append("average     " + " ".join(f"{x:8.3f}" for x in self.per_actor))
        lines.append(
            f"actor average (aAvg) {self.actor_average:.4f}   frame-weighted (gAvg) {self.frame_weighted:.4f}"
        )
        return "\n".join(lines)


def pcp(
    gt: np.ndarray, pred: np.ndarray, skeleton: str | Skeleton = CANONICAL, alpha: float = 0.5
) -> PCPResult:
    """PCP in 3D (see module doc). gt (T,G,J,3), pred (T,K,J,3)."""
    skel = get_skeleton(skeleton)
    limbs = skel.pcp_limbs()
    T, G, J = gt.shape[:3]
    correct = {k: np.zeros(G) for k in limbs}
    n_frames = np.zeros(G)
    for t in range(T):
        g_idx = np.flatnonzero(_present(gt[t]))
        if len(g_idx) == 0:
            continue
        k_idx = np.flatnonzero(_present(pred[t])) if pred.shape[1] else np.zeros(0, int)
        d = (
            mean_joint_distance(gt[t, g_idx], pred[t, k_idx])
            if len(k_idx)
            else np.full((len(g_idx), 0), np.inf)
        )
        for gi, g in enumerate(g_idx):
            n_frames[g] += 1
            if d.shape[1] == 0 or not np.isfinite(d[gi]).any():
                continue
            p = pred[t, k_idx[int(np.argmin(d[gi]))]]
            for k, pairs in limbs.items():
                for a, b in pairs:
                    ga, gb = gt[t, g, a], gt[t, g, b]
                    length = np.linalg.norm(ga - gb)
                    err = 0.5 * (np.linalg.norm(p[a] - ga) + np.linalg.norm(p[b] - gb))
                    if np.isfinite(err) and np.isfinite(length) and err <= alpha * length:
                        correct[k][g] += 0.5  # two limbs (left, right) per type
    per_limb = {k: np.where(n_frames > 0, v / np.maximum(n_frames, 1), np.nan) for k, v in correct.items()}
    per_actor = np.nanmean(np.stack(list(per_limb.values())), 0) if G else np.zeros(0)
    seen = n_frames > 0
    total = sum(v for v in correct.values())
    return PCPResult(
        per_actor_limb=per_limb,
        per_actor=per_actor,
        actor_average=float(np.mean(per_actor[seen])) if seen.any() else float("nan"),
        frame_weighted=float(total[seen].sum() / (len(limbs) * n_frames[seen].sum()))
        if seen.any()
        else float("nan"),
        n_frames=n_frames,
    )


def mpjpe(gt: np.ndarray, pred: np.ndarray, max_dist_m: float = 0.5) -> dict[str, float]:
    """MPJPE (mean over joints, then poses) of per-frame matched poses (Hungarian on mean joint distance,
    matches above ``max_dist_m`` count as missed). Returns mpjpe_m, median_m, missed (fraction of
    actor-frames), joints_missing (fraction of GT joints absent in matched predictions)."""
    errs, n_gt, n_missed, j_tot, j_miss = [], 0, 0, 0, 0
    for t in range(gt.shape[0]):
        g_idx = np.flatnonzero(_present(gt[t]))
        k_idx = np.flatnonzero(_present(pred[t])) if pred.shape[1] else np.zeros(0, int)
        n_gt += len(g_idx)
        if len(g_idx) == 0:
            continue
        if len(k_idx) == 0:
            n_missed += len(g_idx)
            continue
        d = mean_joint_distance(gt[t, g_idx], pred[t, k_idx])
        r, c = linear_sum_assignment(np.where(np.isfinite(d), d, 1e9))
        ok = d[r, c] <= max_dist_m
        n_missed += len(g_idx) - ok.sum()
        for gi, ki in zip(r[ok], c[ok], strict=True):
            e = np.linalg.norm(gt[t, g_idx[gi]] - pred[t, k_idx[ki]], axis=-1)
            gj = np.isfinite(gt[t, g_idx[gi]]).all(-1)
            j_tot += gj.sum()
            j_miss += (gj & ~np.isfinite(e)).sum()
            errs.append(np.nanmean(e))
    errs = np.asarray(errs)
    return {
        "mpjpe_m": float(np.mean(errs)) if len(errs) else float("nan"),
        "median_m": float(np.median(errs)) if len(errs) else float("nan"),
        "missed": float(n_missed / max(n_gt, 1)),
        "joints_missing": float(j_miss / max(j_tot, 1)),
    }


@dataclass
class MOTResult:
    mota: float
    motp_m: float
    misses: int
    false_positives: int
    id_switches: int
    n_gt: int
    idf1: float
    idtp: int
    extra: dict = field(default_factory=dict)


def mot_metrics(
    gt: np.ndarray, pred: np.ndarray, threshold_m: float = 0.3, joints: np.ndarray | None = None
) -> MOTResult:
    """CLEAR MOT (MOTA with misses, false positives, identity switches) and IDF1.

    gt (T,G,J,3): identity = index along G; pred (T,K,J,3): identity = index along K. A pair matches
    when the mean distance over shared ``joints`` (default all) is at most ``threshold_m``. Per frame,
    last frame's correspondences are kept while still valid, the rest are assigned by the Hungarian
    method (Bernardin & Stiefelhagen 2008). IDF1 (Ristani et al. 2016) from the global identity
    assignment that maximises the frames matched within the threshold.
    """
    if joints is not None:
        gt, pred = gt[:, :, joints], pred[:, :, joints]
    T, G = gt.shape[:2]
    K = pred.shape[1]
    misses = fps_ = idsw = n_gt = 0
    dsum, nmatch = 0.0, 0
    last: dict[int, int] = {}  # gt -> pred of the last match
    overlap = np.zeros((G, K))
    n_pred = 0
    for t in range(T):
        g_idx = np.flatnonzero(_present(gt[t]))
        k_idx = np.flatnonzero(_present(pred[t])) if K else np.zeros(0, int)
        n_gt += len(g_idx)
        n_pred += len(k_idx)
        if len(g_idx) == 0 or len(k_idx) == 0:
            misses += len(g_idx)
            fps_ += len(k_idx)
            continue
        d = mean_joint_distance(gt[t, g_idx], pred[t, k_idx])  # (g,k)
        ok = d <= threshold_m
        overlap[np.ix_(g_idx, k_idx)] += ok
        match: dict[int, int] = {}
        pos_g = {g: i for i, g in enumerate(g_idx)}
        pos_k = {k: i for i, k in enumerate(k_idx)}
        for g, k in last.items():  # keep valid correspondences
            if g in pos_g and k in pos_k and ok[pos_g[g], pos_k[k]]:
                match[g] = k
        free_g = [i for i, g in enumerate(g_idx) if g not in match]
        used_k = set(match.values())
        free_k = [i for i, k in enumerate(k_idx) if k not in used_k]
        if free_g and free_k:
            sub = d[np.ix_(free_g, free_k)]
            r, c = linear_sum_assignment(np.where(sub <= threshold_m, sub, 1e9))
            for ri, ci in zip(r, c, strict=True):
                if sub[ri, ci] <= threshold_m:
                    match[g_idx[free_g[ri]]] = k_idx[free_k[ci]]
        for g, k in match.items():
            if g in last and last[g] != k:
                idsw += 1
            last[g] = k
            dsum += d[pos_g[g], pos_k[k]]
            nmatch += 1
        misses += len(g_idx) - len(match)
        fps_ += len(k_idx) - len(match)
    if G and K:
        r, c = linear_sum_assignment(-overlap)
        idtp = int(overlap[r, c].sum())
    else:
        idtp = 0
    idf1 = 2 * idtp / max(n_gt + n_pred, 1)
    mota = 1.0 - (misses + fps_ + idsw) / max(n_gt, 1)
    return MOTResult(
        mota=float(mota),
        motp_m=float(dsum / max(nmatch, 1)),
        misses=misses,
        false_positives=fps_,
        id_switches=idsw,
        n_gt=n_gt,
        idf1=float(idf1),
        idtp=idtp,
        extra={"n_pred": n_pred, "matches": nmatch},
    )
