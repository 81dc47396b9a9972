"""Observation model (eq. 5.6-5.8), stochastic universal resampling per camera pair, joint refinement."""

from __future__ import annotations

import warnings

import numpy as np
from track_helpers import ring_P

from roomcap.keypoints.skeletons import CANONICAL
from roomcap.track import observation as obs

LIMBS = np.asarray(CANONICAL.limbs)


def _setup(rng, n_cams=3):
    P = ring_P(n_cams).astype(np.float32)
    X = (rng.normal(0, 0.25, (19, 3)) + [0.3, -0.2, 1.0]).astype(np.float32)
    uv, z = obs.project(P, X)  # (C,J,2)
    centers, Minv = obs.camera_rays(P)
    kp = uv[None].astype(np.float32)  # (K=1,C,J,2)
    sc = np.full((1, n_cams, 19), 0.9, np.float32)
    return P, X, centers, obs.ray_basis(Minv, kp), sc


def test_scores_peak_at_truth_and_fall_off(rng):
    P, X, centers, B, sc = _setup(rng)
    offsets = np.float32([0.0, 0.02, 0.05, 0.2])
    S = (X[None] + offsets[:, None, None] * np.float32([1, 0, 0]))[None]  # (1,4,J,3)
    conf = obs.joint_scores(S, centers, B, sc, np.full(3, 1000, np.float32), 0.05, 3.0)  # (1,C,J,4)
    assert np.allclose(conf[..., 0], 0.9, atol=1e-3)
    m = conf.mean((0, 1, 2))
    assert np.all(np.diff(m) < 0)  # monotone in the distance
    lp = obs.log_phi_pairs(obs.limb_scores(conf, LIMBS, 2), obs.camera_pairs(3), 0.01)  # (1,V,4)
    assert lp.shape == (1, 3, 4) and np.all(np.diff(lp[0], axis=-1) < 0)
    w = obs.normalized_weights(obs.log_phi_all(obs.limb_scores(conf, LIMBS, 2), 0.01))
    assert abs(w.sum() - 1) < 1e-6 and w[0, 0] > 0.5


def test_stochastic_universal_sampling(rng):
    w = rng.random((4, 50))
    w /= w.sum(1, keepdims=True)
    counts = np.array([10, 20, 0, 50])
    idx = obs.stochastic_universal_indices(w, counts, rng)
    assert len(idx) == 80 and idx.min() >= 0 and idx.max() < 50
    # SUS: every index is drawn floor(n w) or ceil(n w) times (low variance)
    row3 = np.bincount(idx[30:], minlength=50)
    assert np.all(np.abs(row3 - 50 * w[3]) < 1.0 + 1e-9)
    one = np.zeros((1, 50))
    one[0, 7] = 1
    assert set(obs.stochastic_universal_indices(one, np.array([30]), rng)) == {7}
    # per camera pair: V pairs each draw N/V samples
    lp = np.log(rng.random((2, 3, 300)))
    assert obs.resample_pairs(lp, rng).shape == (2, 300)
    assert obs.pair_sizes(300, 7).sum() == 300


def test_guided_targets_triangulate_and_keep_depth(rng):
    P, X, centers, B, sc = _setup(rng)
    S = (X[None, None] + rng.normal(0, 0.05, (1, 20, 19, 3))).astype(np.float32)
    T = obs.guided_targets(S, centers, B, sc)  # (1,J,3,N)
    err = np.linalg.norm(T[0].transpose(2, 0, 1) - X[None], axis=-1)
    assert err.max() < 0.005  # 3 views: the triangulated joint (measured ~1e-3 m with the regulariser)
    one = sc.copy()
    one[:, 1:] = 0  # a single view: onto the ray, depth kept
    T1 = obs.guided_targets(S, centers, B, one)[0].transpose(2, 0, 1)  # (N,J,3)
    r = B[0, :, 6]  # camera 0's unit rays (rows 2C.. of the basis), (J,3)
    a = T1 - centers[0]
    perp = np.linalg.norm(a - (a * r).sum(-1, keepdims=True) * r, axis=-1)
    assert perp.max() < 0.003
    depth_before = ((S[0] - centers[0]) * r).sum(-1)
    assert np.abs((a * r).sum(-1) - depth_before).max() < 0.01


def test_refinement_moves_joints_to_the_evidence(rng):
    P, X, centers, B, sc = _setup(rng)
    S = (X[None, None] + rng.normal(0, 0.05, (1, 100, 19, 3))).astype(np.float32)
    f = np.full(3, 1000, np.float32)
    e0 = np.linalg.norm(S - X, axis=-1).mean()
    R, _ = obs.refine_joints(S, centers, B, sc, f, 0.05, 3.0, 6, 0.03, rng, n_guided=0)
    e1 = np.linalg.norm(R - X, axis=-1).mean()
    G, score = obs.refine_joints(S, centers, B, sc, f, 0.05, 3.0, 6, 0.03, rng, n_guided=3)
    e2 = np.linalg.norm(G - X, axis=-1).mean()
    assert e1 < 0.9 * e0  # random candidates (the seed's): measured 0.080 -> 0.066 m
    assert e2 < 0.3 * e0  # with guided candidates: measured 0.080 -> 0.006 m
    none = np.zeros_like(sc)  # no evidence: nothing moves
    assert np.array_equal(obs.refine_joints(S, centers, B, none, f, 0.05, 3.0, 6, 0.03, rng, 3)[0], S)
    assert score.shape == (1, 19, 100) and score.mean() > 0.8 * 3 * 0.9  # near the peak in all 3 views


def test_association_one_detection_per_track(rng):
    P = ring_P(3).astype(np.float32)
    A = (rng.normal(0, 0.2, (19, 3)) + [1.0, 0, 1]).astype(np.float32)
    Bp = (rng.normal(0, 0.2, (19, 3)) + [-1.0, 0.5, 1]).astype(np.float32)
    uv, z = obs.project(P, np.stack([A, Bp]))  # (C,2,J,2)
    det = uv[:, ::-1].copy()  # detections in the other order
    sc = np.full(det.shape[:3], 0.9, np.float32)
    a = obs.associate(uv, z, det, sc, np.full(3, 1000.0), 0.1, 3.0, 3, 0.1)
    assert np.array_equal(a, np.tile([1, 0], (3, 1)))
    far = det + 300.0
    assert (obs.associate(uv, z, far, sc, np.full(3, 1000.0), 0.1, 3.0, 3, 0.1) == -1).all()


def test_heatmap_and_paf_scores_eq_5_8():
    H, W = 60, 80
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    a, b = np.float32([20, 30]), np.float32([60, 30])
    heat = np.stack([np.exp(-((xx - p[0]) ** 2 + (yy - p[1]) ** 2) / 8.0) for p in (a, b)])  # (2,H,W)
    paf = np.zeros((1, 2, H, W), np.float32)
    band = (np.abs(yy - 30) < 3) & (xx >= 20) & (xx <= 60)
    paf[0, 0][band] = 1.0  # unit vector along +x on the limb
    limbs = np.array([[0, 1]])
    good = np.stack([a, b])[None]  # (1,J=2,2) in map pixels (px_to_map = 1)
    flipped = np.stack([b, a])[None]
    off = good + np.float32([0, 10])
    s_good = obs.heatmap_limb_scores(good, heat, paf, limbs, limbs, 1.0)
    s_flip = obs.heatmap_limb_scores(flipped, heat, paf, limbs, limbs, 1.0)
    s_off = obs.heatmap_limb_scores(off, heat, paf, limbs, limbs, 1.0)
    assert s_good[0, 0] > 0.9 and s_flip[0, 0] < 0.05 and s_off[0, 0] < 0.05


def test_log_phi_pairs_broadcast_equals_gather(rng):
    """The per-first-camera broadcast (the filter's path for camera_pairs) equals the gather over any pair
    list, bit for bit, zero scores of unseen cameras included (eps 0.01: groups of 8 limbs); a custom pair
    list takes the gather."""
    phi = (rng.random((3, 7, 18, 20)) ** 3).astype(np.float32)
    phi[:, 5:] = 0.0
    pairs = obs.camera_pairs(7)
    fast = obs.log_phi_pairs(phi, pairs, 0.01)
    ref = obs._log_phi_pairs_gather(phi * phi, pairs, 0.01, 8)
    assert fast.shape == (3, 21, 20) and np.array_equal(fast, ref)
    sub = pairs[::4]
    assert np.array_equal(
        obs.log_phi_pairs(phi, sub, 0.01), obs._log_phi_pairs_gather(phi * phi, sub, 0.01, 8)
    )


def test_nanmedian_last_equals_numpy(rng):
    x = rng.normal(0, 1, (40, 7, 9))
    x[rng.random(x.shape) < 0.4] = np.nan
    x[3, 2] = np.nan  # a row without any value
    x[5, 1, :] = rng.normal(0, 1, 9)  # a full row (odd count); other rows have even and odd counts
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN row
        ref = np.nanmedian(x, -1)
    got = obs.nanmedian_last(x)
    assert np.isnan(got[3, 2])
    assert np.array_equal(got, ref, equal_nan=True)  # the same bits


def test_ray_coords_of_resampled_samples_are_the_gathered_columns(rng):
    """The update recomputes the kept samples' ray coordinates instead of gathering them (cheaper); the two
    must give the same bits (one batched product per sample column)."""
    K, N, J, C = 5, 300, 19, 12
    P = ring_P(C).astype(np.float32)
    X = (rng.normal(0, 0.3, (K, N, J, 3)) + [0.2, 0.1, 1.0]).astype(np.float32)
    centers, Minv = obs.camera_rays(P)
    uv, _ = obs.project(P, X[:, 0])  # (C,K,J,2)
    B = obs.ray_basis(Minv, np.moveaxis(uv, 0, 1).astype(np.float32))
    idx = rng.integers(0, N, (K, N))
    Y = obs.ray_coords(X, centers, B)
    gathered = np.take_along_axis(Y, idx[:, None, None, :], -1)
    assert np.array_equal(obs.ray_coords(X[np.arange(K)[:, None], idx], centers, B), gathered)
