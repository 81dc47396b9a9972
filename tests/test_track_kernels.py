"""The particle filter's compiled kernels (track.kernels) against the numpy reference of each chain.

Fused float32 arithmetic rounds differently from numpy's passes, so the kernels agree with the reference
to float32 rounding (bounds below, measured values beside them), not bit for bit; index-valued results
(resampling, association) agree exactly. Each track is scored on its own: a batch gives the bits of its
tracks run one at a time.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from track_helpers import render_kp, ring_P, walkers

from roomcap.keypoints.skeletons import CANONICAL
from roomcap.track import kernels as kn
from roomcap.track import kernels_gru as kg
from roomcap.track import observation as obs
from roomcap.track.motion import GRUPrior, step_inputs
from roomcap.track.normalize import unrotate_vectors
from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_offline import track_sequence

LIMBS = np.asarray(CANONICAL.limbs)
SM, SPX, EPS = 0.05, 3.0, 0.01


def _scene(rng, K=3, C=5, N=64):
    """K tracks of N samples around K people seen by C ring cameras; camera C-1 misses track 0 and a few
    joints are unseen."""
    P = ring_P(C).astype(np.float32)
    centers, Minv = obs.camera_rays(P)
    people = (rng.normal(0, 0.25, (K, 19, 3)) + rng.uniform(-1, 1, (K, 1, 3)) * [1, 1, 0] + [0, 0, 1]).astype(
        np.float32
    )
    uv, _ = obs.project(P, people)  # (C,K,J,2)
    kp = np.moveaxis(uv, 0, 1).astype(np.float32) + rng.normal(0, 2.0, (K, C, 19, 2)).astype(np.float32)
    sc = rng.uniform(0.3, 1.0, (K, C, 19)).astype(np.float32)
    sc[0, C - 1] = 0.0
    sc[rng.random(sc.shape) < 0.1] = 0.0
    kp[sc == 0] = np.nan
    X = (people[:, None] + rng.normal(0, 0.04, (K, N, 19, 3))).astype(np.float32)
    return X, centers, Minv, kp, sc, np.full(C, 1000.0, np.float32)


def test_ray_basis_and_association_costs_equal_numpy(rng):
    X, centers, Minv, kp, sc, f = _scene(rng)
    B = kn.ray_basis(Minv, kp)
    assert np.abs(B - obs.ray_basis(Minv, kp)).max() < 1e-6  # measured: equal bit for bit
    P = ring_P(5).astype(np.float32)
    muv, mz = obs.project(P, X.mean(1))
    det = np.moveaxis(kp, 0, 1)[:, ::-1].copy()  # (C,D,J,2), detections in the other order
    dsc = np.moveaxis(sc, 0, 1)[:, ::-1].copy()
    kw = dict(tol_m=0.1, min_joints=3, min_score=0.1)
    ref = obs.association_costs(muv, mz, det, dsc, focal_px=f, **kw)
    gate = np.array([3.0, 3.0, 1e9])
    got = kn.association_costs(muv, mz, det, dsc, focal=f, gate=gate, **kw)
    fin = np.isfinite(got)
    assert np.array_equal(got[fin], ref[fin])  # the same bits where computed
    assert fin[ref < gate[None, :, None]].all()  # every cost below its track's gate is computed
    assert np.array_equal(got[:, 2], ref[:, 2])  # an open gate computes all
    a = obs.associate(muv, mz, det, dsc, f, 0.1, 3.0, 3, 0.1)
    assert (a[:-1] == [2, 1, 0]).all()  # camera C-1 has no detection of track 0


def test_pair_weights_equal_eq_5_7_in_numpy(rng):
    X, centers, Minv, kp, sc, f = _scene(rng)
    B = obs.ray_basis(Minv, kp)
    for pairs in (obs.camera_pairs(5), np.array([[0, 0], [3, 1], [4, 4], [2, 4]])):
        Y = obs.ray_coords(X, centers, B)
        conf = obs.joint_scores(X, centers, B, sc, f, SM, SPX, Y)
        ref = obs.log_phi_pairs(obs.limb_scores(conf, LIMBS, 2), pairs, EPS)  # (K,V,N)
        kw = dict(focal=f, sigma_m=SM, sigma_px=SPX, eps=EPS, limbs=LIMBS, pairs=pairs)
        phi = kn.pair_weights(X, centers, B, sc, **kw)
        assert phi.shape == ref.shape and phi.dtype == np.float64
        assert np.abs(np.log(phi) - ref).max() < 1e-4  # measured 1.3e-5
        one = kn.pair_weights(X[1:2], centers, B[1:2], sc[1:2], **kw)
        assert np.array_equal(one, phi[1:2])  # a track's weights do not depend on the batch


def test_sus_indices_equal_numpy_resampling(rng):
    K, V, N = 4, 6, 90
    w = rng.random((K, V, N)) ** 4
    w[2, 3] = 0.0  # a degenerate row: uniform weights
    counts = obs.pair_sizes(N, V)
    u = rng.random(K * V)
    idx = kn.sus_indices(w, counts, u)
    assert idx.shape == (K, N) and idx.min() >= 0 and idx.max() < N
    wn = w / w.sum(-1, keepdims=True).clip(1e-300)
    wn[2, 3] = 1.0 / N

    class Fixed:  # the draws of stochastic_universal_indices: the same u
        def random(self, n):
            return u[:n]

    ref = obs.stochastic_universal_indices(wn.reshape(K * V, N), np.tile(counts, K), Fixed()).reshape(K, N)
    assert (idx == ref).mean() > 0.99  # measured: all equal (float64 cdf here, float32 there)
    assert len(np.unique(idx[2, counts[:3].sum() : counts[:4].sum()])) == counts[3]  # uniform: spread out
    bad = counts.copy()
    bad[0] += 1
    with pytest.raises(ValueError, match="sum to N"):
        kn.sus_indices(w, bad, u)


def test_refinement_equals_numpy_and_its_gather(rng, monkeypatch):
    X, centers, Minv, kp, sc, f = _scene(rng)
    B = obs.ray_basis(Minv, kp)
    K, N = X.shape[:2]
    idx = rng.integers(0, N, (K, N))
    M, R = 4, 3
    noise = rng.standard_normal((K, 19, 3, R, N)).astype(np.float32)
    scales = obs.refine_scales(M, 0.03)[1:]
    kw = dict(sigma_m=SM, sigma_px=SPX, scales=scales, n_guided=1, lam=0.01)
    got, score = kn.refine_resampled(X, idx, centers, B, sc, f, noise=noise, refine=True, **kw)

    Xg = X[np.arange(K)[:, None], idx]
    monkeypatch.setattr(obs, "normal_noise", lambda rng, shape, s: noise.reshape(shape) * np.float32(s))
    ref, ref_score = obs.refine_joints(Xg, centers, B, sc, f, SM, SPX, M, 0.03, None, 1)  # the same noise
    d = np.abs(got - ref).max(-1)
    assert d.max() < 1e-3 and (d < 1e-5).mean() > 0.999  # measured: max 3.6e-7 m (a flipped choice: mm)
    assert np.abs(score - ref_score).max() < 1e-4  # measured 8.6e-6 (scores up to 3.8)
    assert np.abs(got - Xg).max() > 0.01  # joints moved
    alone, _ = kn.refine_resampled(
        X[2:], idx[2:], centers, B[2:], sc[2:], f, noise=noise[2:], refine=True, **kw
    )
    assert np.array_equal(alone, got[2:])
    plain, _ = kn.refine_resampled(X, idx, centers, B, sc, f, noise=noise[..., :0, :], refine=False, **kw)
    assert np.array_equal(plain, Xg)  # without refinement: the gather only
    with pytest.raises(ValueError, match="idx"):
        kn.refine_resampled(X, idx + N, centers, B, sc, f, noise=noise, refine=True, **kw)


def test_output_stats_equal_weighted_stats(rng):
    X, *_ = _scene(rng)
    K, N = X.shape[:2]
    score = rng.uniform(0, 3, (K, 19, N)).astype(np.float32)
    has = np.array([True, False, True])
    mean, std = kn.output_stats(X, score, has, EPS)
    lp = np.where(has[:, None], np.log(score + np.float32(EPS)).sum(1), 0.0)
    rm, rs = obs.weighted_stats(X, lp)
    assert np.abs(mean - rm).max() < 1e-5 and np.abs(std - rs).max() < 1e-6  # measured 4.8e-7, 1.5e-8


def test_gru_prior_equals_the_torch_cell(rng):
    pr = GRUPrior.load(fps=25.0, sigma_m=0.0, dropout=0.0)
    x = walkers(1, 40, seed=2)[20:, 0].astype(np.float32)  # (20,J,3) poses as samples
    prev = walkers(1, 40, seed=2)[19:39, 0].astype(np.float32)
    state = {"prev": prev, "h": (rng.normal(0, 0.3, (20, pr.model.hidden))).astype(np.float32)}
    new, st = pr.predict(x, state, np.random.default_rng(0))
    xh, vh, origin, theta = step_inputs(x, prev, 25.0, pr.model_fps)
    with torch.no_grad():
        h = pr.model.cell(torch.from_numpy(np.concatenate([xh, vh], -1)), torch.from_numpy(state["h"]))
        delta = pr.model.out(h).numpy().reshape(20, -1, 3)
    ref = unrotate_vectors(delta, theta) + x
    assert np.abs(st["h"] - h.numpy()).max() < 1e-6  # measured 9e-8
    assert np.abs(new - ref).max() < 1e-6  # metres; measured 1.2e-7


def test_exp_and_tanh_within_two_ulp():
    x = np.concatenate([np.linspace(-80, 80, 3001), np.linspace(-1, 1, 2001)]).astype(np.float32)
    e = np.array([kg._exp(v) for v in x], np.float64)
    t = np.array([kg._tanh(v) for v in x], np.float64)
    ref_e, ref_t = np.exp(x.astype(np.float64)), np.tanh(x.astype(np.float64))
    ulp = lambda a, r: np.abs(a - r) / np.spacing(np.abs(r).astype(np.float32)).astype(np.float64)  # noqa: E731
    assert ulp(e, ref_e).max() <= 2  # measured 0.92
    assert np.nanmax(ulp(t, ref_t)[ref_t != 0]) <= 3  # measured 1.03


@pytest.mark.parametrize(
    "opts, bound",
    [  # the worst track's mean joint error, measured (this code and the numpy path before it, alike)
        ({"resample": False}, 0.01),  # 0.0051 m
        ({"refine": False}, 0.3),  # 0.22 m: the seed's "w/o joint refinement" drifts at 60 samples
        ({"refine_candidates": 1}, 0.3),  # the same
        ({"exact_output_weights": True}, 0.01),  # 0.0050 m
        ({"motion": "constant_velocity", "refine_guided": 0}, 0.2),  # 0.12 m
    ],
)
def test_ablations_run_through_the_kernels(opts, bound):
    P = ring_P(3)
    X = walkers(2, 20, seed=3)
    kp, sc = render_kp(P, X, noise_px=1.0, seed=1)
    cfg = ParticleConfig(n_samples=60, smooth_sigma_frames=0.0, **opts)
    res = track_sequence(ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg), kp, sc)
    assert len(res.track_id) == 2
    err = np.nanmean(np.linalg.norm(res.xyz_m[:, :, None] - X[:, None], axis=-1), axis=(0, 3)).min(1)
    assert err.max() < bound
