"""Forecast metrics on constructed cases: MPJPE, NDMS, APD/ADE/FDE, NPSS, SSCP."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab.protocol import render
from roomcap.forecast.lab.toy import walker
from roomcap.keypoints.skeletons import get_skeleton

NAMES = get_skeleton("body19").joint_names


def test_mpjpe_averages_over_joints_and_masks(rng):
    gt = rng.normal(size=(4, 10, 19, 3))
    pred = gt + np.array([0.1, 0, 0])
    pred[0, :, 0] += 5.0  # a wild joint that is masked out
    mask = np.ones((4, 10, 19), bool)
    mask[0, :, 0] = False
    assert np.allclose(M.mpjpe(pred, gt, mask), 0.1)
    assert M.mpjpe(pred, gt).shape == (10,)
    with pytest.raises(ValueError, match="end in 3"):
        M.mpjpe(pred[..., :2], gt[..., :2])


def test_mpjpe_best_of_k_scores_the_closest_sample_of_each_window(rng):
    gt = rng.normal(size=(2, 5, 19, 3))
    y = np.repeat(gt[:, None], 2, 1).copy()
    y[0, 0] += [0.3, 0, 0]  # window 0: samples 0.3 and 0.1 m off; window 1: 0.05 and 0.2 m off
    y[0, 1] += [0, 0.1, 0]
    y[1, 0] += [0, 0, 0.05]
    y[1, 1] += [0.2, 0, 0]
    assert np.allclose(M.mpjpe_best_of_k(y, gt), (0.1 + 0.05) / 2)
    assert np.allclose(M.mpjpe(y, np.broadcast_to(gt[:, None], y.shape)), (0.3 + 0.1 + 0.05 + 0.2) / 4)
    mask = np.ones((2, 5, 19), bool)
    mask[1] = False  # window 1 unknown: only window 0 counts
    assert np.allclose(M.mpjpe_best_of_k(y, gt, mask), 0.1)
    with pytest.raises(ValueError, match="must be"):
        M.mpjpe_best_of_k(y[:, 0], gt)


def test_mpjpe_best_of_k_picks_one_sequence_not_the_best_sample_of_each_frame():
    gt = np.zeros((1, 4, 2, 3))
    y = np.zeros((1, 2, 4, 2, 3))
    y[0, 0, :, :, 0] = np.array([0.1, 0.1, 0.1, 0.45])[:, None]  # close early, far at the end
    y[0, 1, :, :, 0] = 0.2  # steady
    # sample 0 is the closer sequence up to every frame (0.1875 < 0.2 over frames 1-4), so frame 4 scores 0.45
    assert np.allclose(M.mpjpe_best_of_k(y, gt), [0.1, 0.1, 0.1, 0.45])
    y[0, 0, 3, :, 0] = 0.6  # now sample 1 is the closer sequence over frames 1-4 (0.2 < 0.225)
    assert np.allclose(M.mpjpe_best_of_k(y, gt), [0.1, 0.1, 0.1, 0.2])


def test_ndms_pair_direction_and_magnitude():
    x = walker(8)
    assert M.ndms_pair(x, x) == pytest.approx(1.0, abs=1e-4)
    still = np.repeat(x[:1], 8, 0)
    assert M.ndms_pair(x, still) == pytest.approx(0.0, abs=1e-5)  # the reference clamps norms at 1e-7
    back = x[::-1].copy()
    assert M.ndms_pair(x, back) < 0.2  # opposite directions


# Turning hips and shoulders (walker's sway_rad): with a rigid torso the seed's root-centred words would hold
# still joints, which the reference's clamp scores 1/2 against still and below 1 against themselves.
SWAY = 0.15


def _scorer(kappa=8, word_form="root_centred"):
    db = [
        walker(200, phase=p, speed_mps=s, heading_rad=h, sway_rad=SWAY)
        for p, s, h in [(0, 1.2, 0), (1.0, 1.0, 2.0), (2.0, 1.4, -1)]
    ]
    return M.NDMSScorer(db, NAMES, kappa, word_form=word_form)


@pytest.mark.parametrize("word_form", ["root_centred", "word_first_frame"])
def test_ndms_real_far_above_zero_velocity_and_fool(word_form):
    scorer = _scorer(word_form=word_form)
    seq = walker(120, phase=0.5, speed_mps=1.1, heading_rad=0.7, sway_rad=SWAY)
    obs, fut = seq[:50], seq[50:]
    real = M.ndms(scorer, obs, fut[None])
    zero = M.ndms(scorer, obs, np.repeat(obs[-1:], 70, 0)[None])
    # fool: many static poses (diverse, one of them the last pose): best-of ADE small, NDMS low
    static = np.stack([np.repeat(seq[i : i + 1], 70, 0) for i in range(0, 120, 5)])
    fool = M.ndms(scorer, obs, static)
    assert real > 0.6  # measured 0.87
    assert zero < 0.15  # measured 0.05 (only the words that include observed frames move)
    assert fool < 0.15
    assert M.apd(static) > 0.3 and M.apd(static) > 10 * M.apd(fut[None].repeat(2, 0))
    curve = scorer.score_forecast(obs, np.repeat(obs[-1:], 70, 0)[None])
    assert curve.shape == (70,) and curve[-1] == pytest.approx(0.0, abs=1e-5)


def test_apd_ade_fde():
    a = np.zeros((3, 5, 2, 3))
    a[1] += [1, 0, 0]
    a[2] += [0, 2, 0]
    # pairwise over flattened (5*2*3) vectors: |a0-a1| = sqrt(10), |a0-a2| = sqrt(40), |a1-a2| = sqrt(50)
    assert M.apd(a) == pytest.approx((np.sqrt(10) + np.sqrt(40) + np.sqrt(50)) / 3)
    assert M.apd(a[:1]) == 0.0
    gt = np.zeros((5, 2, 3)) + [1, 0, 0]
    assert M.ade(a, gt) == pytest.approx(0.0) and M.fde(a, gt) == pytest.approx(0.0)
    assert M.ade(a[[0, 2]], gt) == pytest.approx(np.sqrt(2))


def test_npss_zero_for_identical_positive_for_other_frequency():
    t = np.arange(100) / 25
    g = np.cos(2 * np.pi * 1.0 * t)[None, :, None] * np.ones((2, 1, 6))
    p = np.cos(2 * np.pi * 3.0 * t)[None, :, None] * np.ones((2, 1, 6))
    assert M.npss(g, g) == pytest.approx(0.0, abs=1e-9)
    assert M.npss(p, g) > 0.5  # measured 2.0 (cumulative spectra far apart)
    assert M.npss(g * 2 + 0.1 * p, g) < M.npss(p, g)
    # the reference code squares the real part of the DFT: a sine's spectrum (imaginary) carries no power
    sin_g = np.sin(2 * np.pi * 1.0 * t)[None, :, None] * np.ones((2, 1, 6))
    assert M.npss(p, sin_g + 1e-3 * g) == pytest.approx(M.npss(p, g), abs=1e-6)


def test_sscp_states_and_js_distance():
    a = walker(10, start=(0, 0), heading_rad=0.0)  # faces +y
    b = walker(10, start=(0, 1.5), heading_rad=np.pi)  # 1.5 m ahead, facing -y: they face each other
    c = walker(10, start=(0, -6), heading_rad=np.pi)  # far away
    s_face = M.default_social_state(np.stack([a, b], 1), NAMES)
    s_far = M.default_social_state(np.stack([a, c], 1), NAMES)
    assert s_face[0] == 9 + 3  # near, one mutual facing pair
    assert s_far[0] == 0
    p = M.state_transition_matrix([0, 0, 1, 1, 2], 3)
    assert p.sum() == 4 and p[0, 1] == 1
    assert M.js_distance(p, p) == pytest.approx(0.0, abs=1e-9)
    assert M.js_distance([1, 0], [0, 1]) == pytest.approx(1.0)
    sscp = M.SSCP(lambda X: M.default_social_state(X, NAMES), M.N_DEFAULT_STATES)
    assert sscp.distance([np.stack([a, b], 1)], [np.stack([a, c], 1)]) == pytest.approx(1.0)
    assert sscp.distance([np.stack([a, b], 1)], [np.stack([a, b], 1)]) == pytest.approx(0.0, abs=1e-9)


def test_evaluation_report_ranks_real_above_zero_velocity(tmp_path):
    from roomcap.forecast.lab import data as D
    from roomcap.forecast.lab import evaluate as E
    from roomcap.forecast.runtime.models import ConstantVelocity, ZeroVelocity

    clips = [
        D.Clip(f"w{i}", walker(150, phase=i, speed_mps=1.0 + 0.1 * i, heading_rad=i, sway_rad=SWAY), 25.0)
        for i in range(4)
    ]
    models = {"zero_velocity": ZeroVelocity(), "constant_velocity": ConstantVelocity(), "real": E.Real()}
    res = E.evaluate_single(models, clips, n_obs=25, n_pred=50, n_samples=2, stride=25, max_windows=8)
    r = res["models"]
    assert r["real"]["ndms_mean"] > 0.5 and r["zero_velocity"]["ndms_mean"] < 0.1  # measured 0.93 / 0.02
    assert r["constant_velocity"]["mpjpe"][-1] > r["constant_velocity"]["mpjpe"][0]
    assert np.allclose(r["zero_velocity"]["mpjpe_best_of_k"], r["zero_velocity"]["mpjpe"])  # deterministic
    path = E.write_report(res, tmp_path)
    text = path.read_text()
    assert "MPJPE 400 ms" in text and "NDMS 2 s" in text and "best-of-2 MPJPE 400 ms" in text
    assert (tmp_path / "ndms.png").stat().st_size > 1000 and (tmp_path / "mpjpe.png").exists()


def test_evaluation_intervals_paired_differences_and_repeatability():
    import torch

    from roomcap.forecast.lab import data as D
    from roomcap.forecast.lab import evaluate as E
    from roomcap.forecast.runtime.models import ConstantVelocity, ZeroVelocity

    class Noisy(torch.nn.Module):  # a stochastic stand-in: constant velocity plus sampled noise
        stochastic = True

        def sample(self, obs, n_pred, n_samples=1, **_):
            y = ConstantVelocity().sample(obs, n_pred, n_samples)
            return y + 0.02 * torch.randn(y.shape)

    clips = [
        D.Clip(f"w{i}", walker(130, phase=i, speed_mps=0.9 + 0.1 * i, heading_rad=i), 25.0) for i in range(5)
    ]
    models = {"zero_velocity": ZeroVelocity(), "constant_velocity": ConstantVelocity(), "noisy": Noisy()}
    kw = dict(n_obs=25, n_pred=75, n_samples=3, stride=10, max_windows=30, reference="constant_velocity")
    res = E.evaluate_single(models, clips, **kw)
    assert res["n_clips"] == 5 and res["reference"] == "constant_velocity"
    for r in res["models"].values():
        for m, lo, hi in r["ndms_at"].values():
            assert lo <= m <= hi
    zv, cv = res["models"]["zero_velocity"], res["models"]["constant_velocity"]
    assert set(zv["ndms_at"]) == {"0.4", "1", "2", "3"} and "ndms_diff_at" not in cv
    d = zv["ndms_diff_at"]["2"]
    assert d[2] < 0 and d[0] == pytest.approx(zv["ndms_at"]["2"][0] - cv["ndms_at"]["2"][0])
    # sampling is seeded: evaluating again gives the same figures
    again = E.evaluate_single(models, clips, **kw)
    assert again["models"]["noisy"]["ndms"] == res["models"]["noisy"]["ndms"]
    assert "Δ 2 s" in render(E.as_results(res, "t"))
