"""Intention labels for training the intention model (Tanke sec. 6.2.3): k-means over (per-frame
hip-normalised) training poses, then the cluster ids are merged where the training sequences cycle between
them (a cycle A->B->...->A of consecutive run-compressed ids is one motion, e.g. the phases of a gait):
clusters are joined by agglomerative clustering on the symmetrised, row-normalised transition counts until
``n_intentions`` labels remain. (The seed's supplementary describes cycle detection only in words; this is
our reading.)"""

from __future__ import annotations

import numpy as np

from roomcap.forecast.runtime.models.intention import assign


def fit_intention_labels(
    poses: np.ndarray, sequences: list[np.ndarray], n_clusters: int = 32, n_intentions: int = 8, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """poses (N,D) hip-normalised training poses for k-means; sequences: list of (T_i,D) the same kind of
    poses in time order. Returns centres (K,D) and merge (K,) cluster -> intention label."""
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.cluster.vq import kmeans2

    rng = np.random.default_rng(seed)
    sub = poses[rng.choice(len(poses), min(len(poses), 20000), replace=False)].astype(np.float64)
    centres, _ = kmeans2(sub, n_clusters, minit="++", seed=seed)
    K = len(centres)
    trans = np.zeros((K, K))
    for seq in sequences:
        ids = assign(centres, seq)
        runs = ids[np.r_[True, ids[1:] != ids[:-1]]]  # run-compressed cluster-id sequence
        np.add.at(trans, (runs[:-1], runs[1:]), 1.0)
    P = trans / np.maximum(trans.sum(1, keepdims=True), 1)
    A = P + P.T  # clusters visited in cycles link both ways
    dist = 1.0 - A / max(A.max(), 1e-9)
    np.fill_diagonal(dist, 0)
    iu = np.triu_indices(K, 1)
    Z = linkage(dist[iu], method="average")
    merge = fcluster(Z, t=min(n_intentions, K), criterion="maxclust") - 1
    return centres.astype(np.float32), merge.astype(np.int64)
