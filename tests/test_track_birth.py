"""The learned birth generator g of sec. 5.2.3 (track.birth): fills missing joints, samples diverge,
skeleton mismatch is refused, and the filter starts tracks with it."""

from __future__ import annotations

import numpy as np
import pytest
from track_helpers import render_kp, ring_P, walkers

from roomcap.keypoints.skeletons import CANONICAL, get_skeleton
from roomcap.track.priors import TEMPLATE_BODY19_M

torch = pytest.importorskip("torch")

DROP = [CANONICAL.index(n) for n in ("left_wrist", "right_elbow", "right_wrist", "left_ankle", "nose")]


@pytest.fixture(scope="module")
def gen():
    from roomcap.track.birth import DEFAULT_CHECKPOINT, BirthGenerator

    torch.set_num_threads(1)
    assert DEFAULT_CHECKPOINT.exists() and DEFAULT_CHECKPOINT.stat().st_size < 500_000
    return BirthGenerator.load()


def test_fills_missing_joints_and_samples_diverge(gen):
    from roomcap.track.normalize import denormalize, hip_frame

    X = walkers(1, 40, seed=7)[::8, 0]  # (5,J,3) poses of the procedural walker (not mocap)
    rng = np.random.default_rng(0)
    e_net, e_tmpl = [], []
    for x in X:
        cand = x.copy()
        cand[DROP] = np.nan
        s = gen.sample(cand, 200, rng)
        assert s.shape == (200, 19, 3) and np.isfinite(s).all()
        keep = np.setdiff1d(np.arange(19), DROP)
        assert np.array_equal(s[0, keep], cand[keep])  # sample 0: the observed joints exactly
        e_net.append(np.linalg.norm(s[0, DROP] - x[DROP], axis=-1).mean())
        o, th = hip_frame(x[None])
        e_tmpl.append(
            np.linalg.norm(denormalize(TEMPLATE_BODY19_M[None], o, th)[0, DROP] - x[DROP], -1).mean()
        )
        spread = s.std(0).mean(-1)  # (J,)
        assert spread[DROP].mean() > 1.5 * spread[keep].mean()  # dropout: the filled joints spread more
    # the network's fill beats the median template (measured 0.102 vs 0.219 m)
    assert np.mean(e_net) < np.mean(e_tmpl)
    no_hips = X[0].copy()
    no_hips[[CANONICAL.index(n) for n in ("pelvis", "left_hip", "right_hip")]] = np.nan
    assert gen.sample(no_hips, 10, rng) is None


def test_checkpoint_mismatch_is_refused(tmp_path):
    from roomcap.track.birth import BirthGenerator, BirthNet, save_checkpoint
    from roomcap.track.motion import DEFAULT_CHECKPOINT as MOTION
    from roomcap.track.motion import CheckpointMismatch

    coco = get_skeleton("coco17")
    bad = tmp_path / "coco.pt"
    save_checkpoint(bad, BirthNet(coco.n_joints, 8, 0.2), coco, {})
    with pytest.raises(CheckpointMismatch, match="coco17.*17 joints.*body19.*19 joints"):
        BirthGenerator.load(bad)
    with pytest.raises(CheckpointMismatch, match="expected a 'birth_mlp/1' checkpoint"):
        BirthGenerator.load(MOTION)
    with pytest.raises(FileNotFoundError, match="train_birth"):
        BirthGenerator.load(tmp_path / "missing.pt")


def test_filter_starts_tracks_with_the_generator():
    from roomcap.track.particle import ParticleTracker
    from roomcap.track.particle_config import ParticleConfig
    from roomcap.track.particle_offline import track_sequence

    P = ring_P(3)
    X = walkers(2, 40, seed=3)
    kp, sc = render_kp(P, X, noise_px=1.0, seed=1, drop=0.2)  # 20 % of the joints missing
    cfg = ParticleConfig(motion="constant_velocity", n_samples=150, smooth_sigma_frames=0.0, birth="learned")
    tr = ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg)
    assert tr.birth is not None
    res = track_sequence(tr, kp, sc)
    assert len(res.track_id) == 2 and np.isfinite(res.xyz_m).all()
    for k in range(2):
        e = np.linalg.norm(res.xyz_m[:, k, None] - X, axis=-1).mean((0, 2)).min()
        assert e < 0.04  # measured 0.0064 m (Gaussian birth: 0.0064 m)
    with pytest.raises(ValueError, match="birth must be one of"):
        ParticleConfig(birth="template")
