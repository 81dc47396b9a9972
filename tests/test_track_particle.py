"""The particle filter (seed ch. 5) on hand-made scenes: identities, coasting, camera loss, re-entry."""

from __future__ import annotations

import numpy as np
import pytest
from track_helpers import render_kp, ring_P, walkers

from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_offline import track_sequence
from roomcap.track.trackfile import OBSERVED, PREDICTED

FOCAL = np.full(3, 1000.0)
FAST = dict(motion="constant_velocity", n_samples=150, smooth_sigma_frames=0.0)


def _match(xyz, gt):
    """Mean joint error of every track against its closest person. xyz (T,K,J,3), gt (T,P,J,3)."""
    out = []
    for k in range(xyz.shape[1]):
        d = np.nanmean(np.linalg.norm(xyz[:, k, None] - gt, axis=-1), axis=(0, 2))
        p = int(np.nanargmin(d))
        out.append((p, float(np.nanmean(np.linalg.norm(xyz[:, k] - gt[:, p], axis=-1)))))
    return out


@pytest.fixture(scope="module")
def scene():
    P = ring_P(3)
    X = walkers(2, 60, seed=3)
    kp, sc = render_kp(P, X, noise_px=1.0, seed=1)
    return P, X, kp, sc


def test_tracks_two_people_with_stable_identities(scene):
    P, X, kp, sc = scene
    res = track_sequence(ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST)), kp, sc)
    assert len(res.track_id) == 2
    assert np.isfinite(res.xyz_m).all(-1).all(-1).all()  # both tracked in every frame, one id each
    m = _match(res.xyz_m, X)
    assert sorted(p for p, _ in m) == [0, 1]
    assert max(e for _, e in m) < 0.03  # measured 0.005 m at 1 px noise
    assert (res.flags == OBSERVED).mean() > 0.99


def test_no_detections_coast_with_growing_uncertainty_then_end(scene):
    P, X, kp, sc = scene
    kp, sc = kp.copy(), sc.copy()
    kp[20:], sc[20:] = np.nan, 0.0  # the detector goes blind after frame 20
    cfg = ParticleConfig(**FAST, trim_coast=False, end_after_s=1.0)
    tr = ParticleTracker(P, FOCAL, 25.0, cfg)
    res = track_sequence(tr, kp, sc)
    alive = np.isfinite(res.xyz_m).all(-1).all(-1)  # (T,K)
    assert alive[:45].all() and not alive[46:].any()  # coasts 25 frames (1 s), then ends
    std = res.std_m[:41].mean(axis=(1, 2))
    assert std[40] > 5 * std[19]  # uncertainty grows while coasting (measured 53x)
    assert (res.flags[21:45] == PREDICTED).all()
    assert len(tr.tracks) == 0 and len(tr.lost) == 2
    # offline output drops the coasting frames (default trim_coast)
    res2 = track_sequence(ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST)), kp, sc)
    assert not np.isfinite(res2.xyz_m[21:]).any()


def test_camera_drops_out_and_uncertainty_follows_views(scene):
    P, X, kp, sc = scene
    kp, sc = kp.copy(), sc.copy()
    kp[30:, 2], sc[30:, 2] = np.nan, 0.0  # camera 2 dies mid-sequence
    kp[30:, 1, :, 9:11], sc[30:, 1, :, 9:11] = np.nan, 0.0  # wrists then seen by camera 0 only
    res = track_sequence(ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST)), kp, sc)
    assert len(res.track_id) == 2 and np.isfinite(res.xyz_m).all(-1).all(-1).all()
    assert max(e for _, e in _match(res.xyz_m, X)) < 0.05  # measured 0.014 m
    s1 = np.nanmean(res.std_m[40:][res.n_views[40:] == 1])
    s3 = np.nanmean(res.std_m[5:30][res.n_views[5:30] == 3])
    assert s1 > 3 * s3  # fewer views, larger spread (measured 37x)


def test_person_leaving_and_returning_gets_the_old_identity():
    P = ring_P(3)
    X = walkers(2, 90, seed=5)
    kp, sc = render_kp(P, X, noise_px=1.0, seed=2)
    gone = np.zeros(kp.shape[:3], bool)
    # person 0 leaves for 40 frames (> end_after_s): mask its detections by matching the ground truth
    h = np.einsum("cab,tjb->tcja", P[:, :, :3], X[:, 0]) + P[None, :, None, :, 3]
    uv0 = h[..., :2] / h[..., 2:]
    d = np.nanmean(np.linalg.norm(kp - uv0[:, :, None], axis=-1), -1)  # (T,C,D)
    gone[30:70] = d[30:70] < 20
    kp[gone], sc[gone] = np.nan, 0.0
    cfg = ParticleConfig(**FAST, end_after_s=0.8)
    tr = ParticleTracker(P, FOCAL, 25.0, cfg)
    res = track_sequence(tr, kp, sc)
    assert len(res.track_id) == 2  # the returning person is not a new identity
    alive = np.isfinite(res.xyz_m).all(-1).all(-1)
    m = dict(_match(res.xyz_m, X))
    k0 = [k for k in range(2) if _match(res.xyz_m[:, k : k + 1], X)[0][0] == 0][0]
    assert not alive[35:70, k0].any() and alive[75:, k0].all()
    assert all(e < 0.05 for e in m.values())


def test_config_rejects_unknown_keys_and_single_camera_rig():
    with pytest.raises(ValueError, match="unknown keys.*n_particles.*valid keys"):
        ParticleConfig.from_dict({"n_particles": 10})
    with pytest.raises(ValueError, match="motion must be one of"):
        ParticleConfig(motion="kalman")
    tr = ParticleTracker(ring_P(1), np.full(1, 1000.0), 25.0, ParticleConfig(**FAST))
    assert tr.reconstructor is None  # cannot start tracks from one view, but runs
    est = tr.step(np.full((1, 0, 19, 2), np.nan), np.zeros((1, 0, 19)), 0)
    assert len(est.track_id) == 0
    with pytest.raises(ValueError, match=r"kp must have shape \(C=1"):
        tr.step(np.zeros((2, 1, 19, 2)), np.zeros((2, 1, 19)), 1)
