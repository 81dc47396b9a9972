"""The filter's confidence-map + PAF observation (eq. 5.8) on maps rendered from a synthetic person."""

from __future__ import annotations

import numpy as np
import pytest
from track_helpers import render_kp, render_maps, ring_P, walkers

from track import observation as obs
from track.particle import ParticleConfig, ParticleTracker, track_sequence

FOCAL = np.full(3, 1000.0)
FAST = dict(motion="constant_velocity", n_samples=150, smooth_sigma_frames=0.0)


@pytest.fixture(scope="module")
def scene():
    P = ring_P(3)
    X = walkers(1, 30, seed=5)
    kp, sc = render_kp(P, X, noise_px=1.0, seed=2)
    maps = [render_maps(P, X[t]) for t in range(len(X))]
    return P, X, kp, sc, maps


def test_map_scores_peak_at_the_person(scene):
    P, X, _, _, maps = scene
    offsets = np.float32([0.0, 0.03, 0.08, 0.3])
    S = (X[0, 0][None] + offsets[:, None, None] * np.float32([1, 0.5, 0]))[None]  # (1,4,J,3)
    phi = obs.map_limb_scores(S, P[0], maps[0][0])  # (1,L,4)
    assert phi.shape == (1, 19, 4)
    m = phi[0].mean(0)
    assert m[0] > 0.5  # measured 0.72 (bilinear on 1-px-wide rendered fields)
    assert np.all(np.diff(m) < 0) and m[-1] < 0.05  # falls off with the distance


def test_filter_uses_the_maps_and_tracks(scene):
    P, X, kp, sc, maps = scene
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    res = track_sequence(tr, kp, sc, maps_at=lambda t: maps[t])
    assert tr.n_map_scores == len(X) - 1  # every update after the birth frame weighed by the maps
    assert len(res.track_id) == 1 and np.isfinite(res.xyz_m).all()
    err = np.linalg.norm(res.xyz_m[:, 0] - X[:, 0], axis=-1)
    assert np.nanmean(err) < 0.03  # measured 0.0048 m (keypoints only: 0.0049 m)
    ref = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    track_sequence(ref, kp, sc)
    assert ref.n_map_scores == 0  # keypoints only without maps


def test_maps_carry_a_camera_without_keypoints(scene):
    """Camera 2 loses its keypoints: with its maps it still weighs the samples (eq. 5.8 per camera)."""
    P, X, kp, sc, maps = scene
    kp, sc = kp.copy(), sc.copy()
    kp[5:, 2], sc[5:, 2] = np.nan, 0.0
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    res = track_sequence(tr, kp, sc, maps_at=lambda t: maps[t])
    err = np.linalg.norm(res.xyz_m[:, 0] - X[:, 0], axis=-1)
    assert np.nanmean(err) < 0.04  # measured 0.0061 m


def test_maps_must_match_the_cameras(scene):
    P, X, kp, sc, maps = scene
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    with pytest.raises(ValueError, match="one entry"):
        tr.step(kp[0], sc[0], 0, maps[0][:2])
