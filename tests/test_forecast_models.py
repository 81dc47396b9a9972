"""Forecast models: shapes, learning, checkpoints (and wrong skeletons), preview, CLI on track files."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from roomcap.core.errors import FormatError, InputError
from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.toy import walker
from roomcap.forecast.runtime.models import ConstantVelocity, SocialDiffusion, ZeroVelocity
from roomcap.forecast.runtime.predict import (
    diffusion_rollout,
    features_to_poses,
    forecast_world,
    scene_features,
)
from roomcap.forecast.runtime.registry import MODELS
from roomcap.keypoints.skeletons import get_skeleton

torch.set_num_threads(1)


def _clips(n=6, T_=160):
    return [
        D.Clip(f"w{i}", walker(T_, phase=i, speed_mps=0.8 + 0.1 * i, heading_rad=i, turn_rps=0.05 * i), 25.0)
        for i in range(n)
    ]


def test_forecasts_continue_the_last_observed_velocity():
    from roomcap.forecast.runtime.predict import continue_velocity

    obs = walker(50, speed_mps=1.2)  # (T,J,3)
    cfg = T.config_from_dict("gru", {"hidden": 16})
    assert cfg.continuity  # the default
    gru = T.build_model(
        "gru", cfg, 19
    )  # untrained: its output layer starts at zero, it repeats the last pose
    y = forecast_world(gru, obs[None, :, None], None, 10)[0, 0, :, 0]
    step = obs[-1] - obs[-2]
    assert np.linalg.norm(step, axis=-1).mean() > 0.03  # the walker moves ~5 cm per frame
    assert np.allclose(y[0], obs[-1] + step, atol=1e-4) and np.allclose(y[-1], y[0], atol=1e-4)
    off = T.build_model("gru", dataclasses.replace(cfg, continuity=False), 19)
    off.load_state_dict(gru.state_dict())
    assert np.allclose(forecast_world(off, obs[None, :, None], None, 10)[0, 0, 0, 0], obs[-1], atol=1e-4)
    # the shift is the same for every frame of a sample: the forecast's own motion is kept
    y = np.random.default_rng(0).normal(size=(2, 3, 4, 5))
    out = continue_velocity(y, np.ones((2, 5)), np.zeros((2, 5)))
    assert np.allclose(out[:, :, 0], 2.0) and np.allclose(np.diff(out, axis=2), np.diff(y, axis=2))


def test_diffusion_sampling_temperature_scales_the_spread_of_the_samples():
    base = {"channels": 16, "n_frames": 32, "n_obs": 16, "sample_steps": 3}
    obs = walker(16)[None, :, None]
    spread = {}
    for temp in (0.0, 1.0, 2.0):
        m = T.build_model(
            "social_diffusion", T.config_from_dict("social_diffusion", {**base, "sample_temp": temp}), 19
        )
        assert m.sample_temp == temp
        torch.manual_seed(0)
        y = forecast_world(m, obs, None, 16, 4)[0, :, :, 0]  # (S,H,J,3)
        spread[temp] = float(np.std(y, axis=0).mean())
    assert spread[0.0] < 1e-6 < spread[1.0] < spread[2.0]  # no noise: one deterministic DDIM path


def test_baselines_in_world_space():
    x = walker(30, heading_rad=0.4, start=(1, 2))[None, :, None]  # (1,T,1,J,3)
    zv = forecast_world(ZeroVelocity(), x, None, 5)
    assert zv.shape == (1, 1, 5, 1, 19, 3) and np.abs(zv[0, 0, :, 0] - x[0, -1, 0]).max() < 1e-5
    cv = forecast_world(ConstantVelocity(), x, None, 3)
    v = x[0, -1, 0] - x[0, -2, 0]
    assert np.abs(cv[0, 0, 2, 0] - (x[0, -1, 0] + 3 * v)).max() < 1e-4


def test_training_and_evaluation_report_through_the_progress_protocol():
    """progress(task, done, total) from the library (core.progress), done reaching total; nothing printed."""
    from roomcap.forecast.lab import evaluate as E

    calls = []
    cfg = T.config_from_dict("gru", {"hidden": 8, "steps": 4, "batch": 4, "n_obs": 10, "n_pred": 5})
    model, _ = T.train("gru", _clips(2, 60), cfg, progress=lambda *a: calls.append(a))
    assert calls == [("train gru", i, 4) for i in range(1, 5)]
    calls.clear()
    models = {"zero": T.baseline("zero"), "gru": model}
    E.evaluate_single(models, _clips(2, 80), n_obs=10, n_pred=10, max_windows=4, n_boot=10,
                      progress=lambda *a: calls.append(a))  # fmt: skip
    assert calls == [("eval models", 0, 2), ("eval models", 1, 2), ("eval models", 2, 2)]


def test_scene_features_round_trip():
    x = walker(20, heading_rad=2.5, start=(0.3, -1))
    f = scene_features(x, anchor=9)
    assert f.shape == (20, 19 * 3 + 10)
    assert np.abs(f[9, 57:60]).max() < 1e-6  # root offset is 0 at the anchor frame
    assert np.abs(features_to_poses(f, 19) - x).max() < 1e-5
    assert np.abs(features_to_poses(f, 19, f[0, 62:]) - x).max() < 1e-5


def test_gru_learns_and_checkpoint_round_trip(tmp_path):
    cfg = T.config_from_dict(
        "gru", {"hidden": 32, "steps": 60, "batch": 16, "n_obs": 20, "n_pred": 10, "lr": 3e-3}
    )
    model, hist = T.train("gru", _clips(), cfg)
    first, last = np.mean(hist["loss"][:5]), np.mean(hist["loss"][-5:])
    assert last < 0.7 * first  # measured 0.094 -> 0.030
    T.save_checkpoint(tmp_path / "g.pt", model, "gru", cfg)
    m2, meta = T.load_checkpoint(tmp_path / "g.pt", skeleton="body19")
    assert meta["skeleton"] == "body19" and meta["config"] == cfg and "hip vector" in meta["normalisation"]
    x = walker(20)[None, :, None]
    assert np.allclose(forecast_world(model, x, None, 7), forecast_world(m2, x, None, 7), atol=1e-6)
    with pytest.raises(FormatError, match="smpl29"):
        T.load_checkpoint(tmp_path / "g.pt", skeleton="smpl29")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="forecast train"):
        T.load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="valid keys"):
        T.config_from_dict("gru", {"hiden": 3})


def test_speed_gap_scores_how_much_slower_or_faster_the_forecast_moves():
    rng = np.random.default_rng(0)
    last = torch.from_numpy(rng.normal(size=(2, 6)).astype(np.float32))  # 2 joints
    step = torch.tensor([0.03, 0.0, 0.04, 0.0, 0.0, 0.05])  # joint speeds 0.05, 0.05
    fut = last[:, None] + step * torch.arange(1, 5)[None, :, None]
    mask = torch.ones(2, 4, 2, dtype=torch.bool)
    assert T.speed_gap(fut, fut, last, mask) == 0
    still = last[:, None].expand(-1, 4, -1)  # a forecast that stops: the whole real speed is missing
    assert float(T.speed_gap(still, fut, last, mask)) == pytest.approx(0.05, abs=1e-6)
    half = last[:, None] + 0.5 * step * torch.arange(1, 5)[None, :, None]
    assert float(T.speed_gap(half, fut, last, mask)) == pytest.approx(0.025, abs=1e-6)
    mask[:, :, 1] = False  # masked joints do not count
    assert float(T.speed_gap(still, fut, last, mask)) == pytest.approx(0.05, abs=1e-6)
    cfg = T.config_from_dict("gru", {"hidden": 16, "steps": 3, "batch": 4, "n_obs": 20, "n_pred": 10})
    assert cfg.w_speed == 0.0  # off by default: the shipped recipes are unchanged
    _, hist = T.train("gru", _clips(2), dataclasses.replace(cfg, w_speed=1.0))
    assert len(hist["loss"]) == 3 and np.isfinite(hist["loss"]).all()


@pytest.mark.slow
def test_intention_model_trains_and_samples_diverse_futures():
    cfg = T.config_from_dict(
        "intention",
        {
            "hidden": 32,
            "z_dim": 8,
            "layers": 2,
            "n_clusters": 8,
            "n_intentions": 3,
            "steps": 25,
            "batch": 8,
            "n_obs": 20,
            "n_pred": 30,
        },
    )
    model, hist = T.train("intention", _clips(4, 120), cfg)
    assert np.isfinite(hist["loss"]).all()
    assert hist["loss"][-1] < hist["loss"][0]  # measured 1.3 -> 0.9 (intention CE dominates early)
    assert int(model.merge.max()) < 3
    y = forecast_world(model, walker(20)[None, :, None], None, 30, n_samples=4)
    assert y.shape == (1, 4, 30, 1, 19, 3) and np.isfinite(y).all()
    assert np.std(y[0, :, -1], axis=0).mean() > 0  # stochastic: samples differ


def test_intention_checkpoint_is_small_and_training_continues_from_it(tmp_path):
    cfg = T.config_from_dict(
        "intention",
        {"hidden": 16, "z_dim": 4, "n_clusters": 6, "n_intentions": 3, "steps": 3, "batch": 4, "n_obs": 20},
    )
    clips = _clips(3, 120)
    model, _ = T.train("intention", clips, cfg)
    T.save_checkpoint(tmp_path / "i.pt", model, "intention", cfg)
    blob = torch.load(tmp_path / "i.pt", weights_only=True)
    assert not any(
        k.startswith(T.DISCRIMINATOR_PREFIXES) for k in blob["weights"]["model"]
    )  # training-only parts
    m2, _ = T.load_checkpoint(tmp_path / "i.pt", skeleton="body19")
    assert torch.equal(m2.centres, model.centres) and torch.equal(m2.merge, model.merge)
    # continue with a longer horizon: labels are kept, discriminators start fresh
    cfg2 = T.config_from_dict("intention", {**dataclasses.asdict(cfg), "n_pred": 60})
    m3, hist = T.train("intention", clips, cfg2, init=blob["weights"]["model"])
    assert torch.equal(m3.centres, model.centres) and np.isfinite(hist["loss"]).all()
    with pytest.raises(ValueError, match="does not fit"):
        T.build_model(
            "intention", T.config_from_dict("intention", {"hidden": 8}), 19, blob["weights"]["model"]
        )


def _small_intention(label_temp=1.0):
    cfg = T.config_from_dict(
        "intention", {"hidden": 16, "z_dim": 4, "n_clusters": 6, "n_intentions": 4, "label_temp": label_temp}
    )
    torch.manual_seed(0)
    m = T.build_model("intention", cfg, 19).eval()
    torch.nn.init.normal_(m.p_out.weight, std=0.01)  # zero at init: the labels would not show in the poses
    return m, cfg


def test_intention_label_temperature_default_samples_as_before(tmp_path):
    import torch.nn.functional as F

    from roomcap.forecast.runtime.models.intention import local_poses

    m, cfg = _small_intention()
    assert cfg.label_temp == 1.0 and m.label_temp == 1.0  # the default: today's samples
    obs = torch.from_numpy(walker(20).reshape(1, 20, 57)).float()

    def before(n_pred=12, S=3):  # sample() as it was before label_temp (commit 8f41f89)
        o = obs.repeat_interleave(S, 0)
        h, c, out = m._label_init(o), F.one_hot(m.labels(local_poses(o)[:, -1]), m.C).float(), []
        for _ in range(n_pred + m.gamma - 1):
            h = m.d_l(c, h)
            c = F.gumbel_softmax(m.l_out(h), tau=1.0, hard=True)
            out.append(c)
        z = torch.randn(S, m.z_dim)
        return m.decode(o, torch.stack(out, 1), n_pred, z).view(1, S, n_pred, -1)

    with torch.no_grad():
        torch.manual_seed(5)
        ref = before()
        torch.manual_seed(5)
        assert torch.equal(m.sample(obs, 12, 3), ref)
        m.label_temp = 2.0
        torch.manual_seed(5)
        assert not torch.equal(m.sample(obs, 12, 3), ref)
        # temperature -> 0: the most likely label at every step, whatever the noise; large: uniform labels
        o, c0 = obs.expand(400, -1, -1), torch.zeros(400, dtype=torch.long)
        cold = [m.label_rollout(o, c0, 20, 1e-6).argmax(-1) for _ in range(2)]
        assert torch.equal(cold[0], cold[1]) and (cold[0] == cold[0][:1]).all()
        freq = torch.bincount(m.label_rollout(o, c0, 20, 1e6).argmax(-1).flatten(), minlength=4) / 8000
        assert freq.min() > 0.2 and freq.max() < 0.3  # 1/4 each (2,000 draws per label expected)
    T.save_checkpoint(tmp_path / "t.pt", m, "intention", dataclasses.replace(cfg, label_temp=1.5))
    assert T.load_checkpoint(tmp_path / "t.pt")[0].label_temp == 1.5  # a config field, kept by checkpoints


def test_intention_noise_scale_scales_the_decoders_noise_only(tmp_path, monkeypatch):
    """``z_scale`` s: the pose decoder gets s z for the same draws (labels unchanged); 1 samples as before."""
    m, cfg = _small_intention()
    assert cfg.z_scale == 1.0 and m.z_scale == 1.0
    obs = torch.from_numpy(walker(20).reshape(1, 20, 57)).float()
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    decode = m.decode

    def spy(o, c, n, z):
        seen.append((c, z))
        return decode(o, c, n, z)

    monkeypatch.setattr(m, "decode", spy)
    with torch.no_grad():
        for s in (1.0, 2.5):
            m.z_scale = s
            torch.manual_seed(5)
            m.sample(obs, 12, 3)
    (c1, z1), (c2, z2) = seen
    assert torch.equal(c1, c2) and torch.allclose(z2, 2.5 * z1) and z1.abs().sum() > 0
    T.save_checkpoint(tmp_path / "t.pt", m, "intention", dataclasses.replace(cfg, z_scale=2.0))
    assert T.load_checkpoint(tmp_path / "t.pt")[0].z_scale == 2.0  # a config field, kept by checkpoints


def test_intention_training_adds_the_joint_speed_term():
    cfg = T.config_from_dict(
        "intention",
        {"hidden": 16, "z_dim": 4, "n_clusters": 6, "n_intentions": 3, "steps": 2, "batch": 4, "n_obs": 20},
    )
    assert cfg.w_speed == 0.0  # off by default: the shipped recipe is unchanged
    clips = _clips(2, 120)
    _, h0 = T.train("intention", clips, cfg)
    _, h1 = T.train("intention", clips, dataclasses.replace(cfg, w_speed=1.0))
    # same seed, same first batch and forecast: the first loss grows by the (positive) speed gap
    assert np.isfinite(h1["loss"]).all() and h1["loss"][0] > h0["loss"][0] + 1e-4


def test_intention_variety_loss_scores_each_windows_closest_noise_draw():
    """``variety`` K: L_rec of each window's closest of K decodes (other z); K = 1 is eq. 6.8 as before."""
    from roomcap.forecast.runtime.registry import intention_model

    cfg = T.config_from_dict(
        "intention",
        {"hidden": 16, "z_dim": 4, "n_clusters": 6, "n_intentions": 3, "n_obs": 20, "n_pred": 30},
    )
    cfg = dataclasses.replace(cfg, continuity=False)  # the decodes as they are
    assert cfg.variety == 1  # off by default: the shipped recipes are unchanged
    torch.manual_seed(0)
    model = intention_model(cfg, 57)
    torch.nn.init.normal_(model.p_out.weight, std=0.3)  # a decoder that uses z (it starts at zero)
    B, K = 6, 4
    obs, fut = torch.randn(B, 20, 57), torch.randn(B, 30, 57)
    mask, lab = torch.rand(B, 30, 19) > 0.3, torch.randint(0, 3, (B, 60))

    def rec(k: int, seed: int) -> tuple[float, torch.Tensor]:
        torch.manual_seed(seed)  # the same label rollout and noise draws
        np.random.seed(seed)
        with torch.no_grad():
            k_cfg = dataclasses.replace(cfg, variety=k)
            _, terms, _, pred = T.intention_losses(model, k_cfg, obs, fut, mask, lab)
        return terms["rec"], pred

    # the K draws, one at a time: z are the rows of one (B*K, z) draw after the label rollout
    torch.manual_seed(1)
    np.random.seed(1)
    with torch.no_grad():
        model.label_rollout(obs, lab[:, 19], 30 + cfg.gamma - 1)
        z = torch.randn(B * K, cfg.z_dim)
        c = torch.nn.functional.one_hot(lab[:, 20:59], 3).float().repeat_interleave(K, 0)
        each = model.decode(obs.repeat_interleave(K, 0), c, 30, z).view(B, K, 30, 19, 3)
    lam = torch.clamp(1 - torch.arange(30.0) / cfg.tau_rec, min=0)
    w = mask.float() * lam[None, :, None]
    per = ((each - fut.view(B, 1, 30, 19, 3)).norm(dim=-1) * w[:, None]).sum((2, 3))  # (B, K)
    r_k, pred_k = rec(K, 1)
    assert r_k == pytest.approx(float(per.min(1).values.sum() / w.sum()), rel=1e-5)
    assert r_k < float(per.mean(1).sum() / w.sum())  # the closest draw, not their mean
    assert pred_k.shape == (B, 30, 57)  # the first draw, for the adversarial and speed terms
    r_1, _ = rec(1, 1)
    assert np.isfinite(r_1) and r_1 > r_k
    # the first stage of the angle benchmark's model is not one of the body19 loop's: said, not ignored
    with pytest.raises(InputError, match="label_steps .* an option of the angle benchmark"):
        T.train("intention", _clips(2, 120), dataclasses.replace(cfg, label_steps=5))


@pytest.mark.slow
def test_social_diffusion_writes_back_observation_and_learns():
    m = SocialDiffusion(62, n_frames=32, channels=16, T=100)
    obs = torch.randn(2, 3, 10, 62)
    out = m.sample_window(obs, torch.tensor([[True, True, False], [True, True, True]]), n_samples=2, steps=5)
    assert out.shape == (2, 2, 3, 32, 62)
    assert torch.allclose(out[:, 0, :, :10], obs, atol=1e-5)
    # the person mean is order invariant: permuting people permutes the output
    x = torch.randn(1, 3, 32, 62)
    t = torch.tensor([50])
    pm = torch.ones(1, 3, dtype=torch.bool)
    a, b = m.g(x, t, pm), m.g(x[:, [2, 0, 1]], t, pm)
    assert torch.allclose(a[:, [2, 0, 1]], b, atol=1e-5)
    cfg = T.config_from_dict(
        "social_diffusion",
        {
            "channels": 16,
            "T": 100,
            "n_frames": 32,
            "n_obs": 16,
            "steps": 40,
            "batch": 8,
            "lr": 2e-3,
            "sample_steps": 4,
        },
    )
    model, hist = T.train("social_diffusion", _clips(4, 100), cfg)
    assert np.mean(hist["loss"][-5:]) < np.mean(hist["loss"][:5])  # measured 0.80 -> 0.55
    scene = np.stack([walker(16), walker(16, start=(2, 0))], 1)[None]
    y = forecast_world(model, scene, None, 40, n_samples=2)  # two windows rolled out
    assert y.shape == (1, 2, 40, 2, 19, 3) and np.isfinite(y).all()


@pytest.mark.slow
def test_diffusion_mirror_option_trains_on_both_sides():
    base = {"channels": 16, "T": 50, "n_frames": 32, "n_obs": 16, "steps": 2, "batch": 4, "val_every": 0}
    base["mirror"] = False
    clips = [D.Clip("turning_left", walker(100, turn_rps=0.2), 25.0)]
    _, plain = T.train("social_diffusion", clips, T.config_from_dict("social_diffusion", base))
    _, mirrored = T.train(
        "social_diffusion", clips, T.config_from_dict("social_diffusion", {**base, "mirror": 1})
    )
    assert mirrored["n_windows"] == 2 * plain["n_windows"] > 0


def test_anchored_diffusion_codes_motion_relative_to_the_last_observed_frame():
    cfg = T.config_from_dict(
        "social_diffusion",
        {"channels": 16, "T": 50, "n_frames": 32, "n_obs": 16, "steps": 3, "batch": 4, "sample_steps": 3},
    )
    assert cfg.anchor
    model, _ = T.train("social_diffusion", _clips(3, 100), cfg)
    assert model.feat_std.shape == (32, 19 * 3 + 10) and model.anchor == 15
    std = model.feat_std[:, :57].mean(1)
    assert std[16] < 0.5 * std[-1]  # the spread of the offsets grows with the lag from the anchor
    scene = np.stack([walker(32), walker(32, start=(2, 0))], 1)[None]
    f = torch.from_numpy(T.diffusion_batch_features(scene, np.ones((1, 2), bool), 16))
    z = model.standardise(f)
    assert torch.allclose(model.unstandardise(z, f[:, :, 15]), f, atol=1e-4)
    out = model.sample_window(f[:, :, :16], torch.ones(1, 2, dtype=torch.bool), n_samples=2, steps=3)
    assert torch.allclose(out[:, 0, :, :16], f[:, :, :16], atol=1e-4)
    # the band-limited sampler keeps the observation and removes frame-to-frame wobble from the forecast
    model.sample_dct = 4
    g = torch.Generator().manual_seed(0)
    lp = model.sample_window(f[:, :, :16], torch.ones(1, 2, dtype=torch.bool), 2, 3, generator=g)
    assert torch.allclose(lp[:, 0, :, :16], f[:, :, :16], atol=1e-4)
    g = torch.Generator().manual_seed(0)
    model.sample_dct = 0
    raw = model.sample_window(f[:, :, :16], torch.ones(1, 2, dtype=torch.bool), 2, 3, generator=g)

    def wobble(y):
        return y[..., 17:, :57].diff(n=2, dim=-2).abs().mean()

    assert wobble(lp) < wobble(raw)


def test_root_velocity_coding_round_trips_and_keeps_the_observation():
    cfg = T.config_from_dict(
        "social_diffusion",
        {
            "channels": 16,
            "T": 50,
            "n_frames": 32,
            "n_obs": 16,
            "steps": 3,
            "batch": 4,
            "sample_steps": 3,
            "root_vel": True,
        },
    )
    model, _ = T.train("social_diffusion", _clips(3, 100), cfg)
    assert model.root_vel and model.anchor == 15
    scene = np.stack([walker(32), walker(32, start=(2, 0))], 1)[None]
    f = torch.from_numpy(T.diffusion_batch_features(scene, np.ones((1, 2), bool), 16))
    c = model.code(f, f[:, :, 15])
    i = 19 * 3  # the root channels are per-frame displacements of the root offsets
    assert torch.allclose(c[..., 1:, i : i + 3], f[..., 1:, i : i + 3] - f[..., :-1, i : i + 3], atol=1e-6)
    assert torch.equal(c[..., :i], model.relative(f, f[:, :, 15])[..., :i])  # the pose: offsets, as before
    assert torch.allclose(model.decode(c, f[:, :, 15]), f, atol=1e-5)  # exact round trip of the window
    z = model.standardise(f)
    assert torch.allclose(model.unstandardise(z, f[:, :, 15]), f, atol=1e-4)
    # root displacements are a few cm per frame: their spread does not grow with the lag like offsets do
    std = model.feat_std[1:, i : i + 2].mean(1)
    assert std.max() < 3 * std.min()
    out = model.sample_window(f[:, :, :16], torch.ones(1, 2, dtype=torch.bool), n_samples=2, steps=3)
    assert torch.allclose(out[:, 0, :, :16], f[:, :, :16], atol=1e-4)  # observed frames written back
    assert torch.isfinite(out).all()
    with pytest.raises(ValueError, match="root_vel"):
        T.build_model(
            "social_diffusion", T.config_from_dict("social_diffusion", {"root_vel": 1, "anchor": 0}), 19
        )


def test_shared_statistics_free_an_anchored_model_from_its_window_length():
    """lag_stats = false: motion still coded relative to the last observed frame, standardised with one
    mean/std per channel shared over time (the seed's), so any length is generated in one pass."""
    base = {"channels": 16, "T": 50, "n_frames": 32, "n_obs": 16, "steps": 3, "batch": 4, "sample_steps": 3}
    model, _ = T.train("social_diffusion", _clips(3, 100), T.config_from_dict("social_diffusion", base))
    shared, _ = T.train(
        "social_diffusion", _clips(3, 100), T.config_from_dict("social_diffusion", {**base, "lag_stats": 0})
    )
    assert model.feat_std.shape == (32, 67) and shared.feat_std.shape == (67,) and shared.anchor == 15
    assert diffusion_rollout(model, 100) == "chained" and diffusion_rollout(shared, 100) == "one_pass"
    scene = np.stack([walker(64), walker(64, start=(2, 0))], 1)[None]  # twice the training window
    f = torch.from_numpy(T.diffusion_batch_features(scene, np.ones((1, 2), bool), 16))
    z = shared.standardise(f)
    k = 67 - 5  # motion channels at the anchor frame are offsets of 0: the shared mean, standardised
    assert torch.allclose(z[:, :, 15, :k], -shared.feat_mean[:k] / shared.feat_std[:k], atol=1e-5)
    assert torch.allclose(shared.unstandardise(z, f[:, :, 15]), f, atol=1e-4)
    out = shared.sample_window(f[:, :, :16], torch.ones(1, 2, dtype=torch.bool), 2, 3, n_frames=64)
    assert out.shape == (1, 2, 2, 64, 67) and torch.isfinite(out).all()
    assert torch.allclose(out[:, 0, :, :16], f[:, :, :16], atol=1e-4)  # observation written back
    with pytest.raises(ValueError, match="per-frame statistics"):
        model.sample_window(f[:, :, :16], torch.ones(1, 2, dtype=torch.bool), 1, 3, n_frames=64)
    y = forecast_world(shared, scene[:, :16], None, 100, n_samples=1)
    assert y.shape == (1, 1, 100, 2, 19, 3) and np.isfinite(y).all()


@pytest.mark.slow
def test_diffusion_ema_weights_are_validated_and_returned():
    base = {"channels": 16, "T": 50, "n_frames": 32, "n_obs": 16, "steps": 4, "batch": 4, "lr": 1e-2}
    clips = _clips(4, 160)  # validation needs 150-frame windows
    init = T.build_model("social_diffusion", T.config_from_dict("social_diffusion", base), 19).state_dict()
    init = {k: v.clone() for k, v in init.items()}
    raw, _ = T.train("social_diffusion", clips[:3], T.config_from_dict("social_diffusion", base), init=init)
    cfg = T.config_from_dict(
        "social_diffusion",
        {**base, "ema": 1 - 1e-9, "val_every": 2, "val_windows": 3, "val_samples": 2, "select": "ndms_2_3"},
    )
    slow, hist = T.train("social_diffusion", clips[:3], cfg, init=init, val_clips=clips[3:])
    w = "inp.weight"
    assert not torch.allclose(raw.state_dict()[w], init[w], atol=1e-4)  # the raw weights moved
    assert torch.allclose(slow.state_dict()[w], init[w], atol=1e-6)  # an average that barely moves did not
    assert [r["step"] for r in hist["val"]] == [2, 4] and hist["val_best"]["select"] == "ndms_2_3"
    assert all(0 <= r["ndms_2_3"] <= 1 for r in hist["val"])


def test_dct_lowpass_is_a_projection_that_keeps_slow_motion():
    from roomcap.forecast.runtime.models.diffusion import dct_lowpass_matrix

    P = dct_lowpass_matrix(32, 6)
    assert torch.allclose(P @ P, P, atol=1e-5) and torch.allclose(P, P.T, atol=1e-6)
    assert torch.allclose(P.trace(), torch.tensor(6.0), atol=1e-4)
    t = torch.arange(32.0)
    slow = torch.cos(torch.pi / 32 * (t + 0.5) * 2)  # DCT basis 2: kept
    fast = torch.cos(torch.pi / 32 * (t + 0.5) * 20)  # DCT basis 20: removed
    assert torch.allclose(P @ slow, slow, atol=1e-4) and (P @ fast).abs().max() < 1e-4
    assert torch.allclose(dct_lowpass_matrix(8, 8), torch.eye(8), atol=1e-5)


def test_training_keeps_the_state_with_the_best_validation_score():
    cfg = T.config_from_dict(
        "gru", {"hidden": 16, "steps": 30, "batch": 8, "n_obs": 20, "n_pred": 10, "val_every": 10}
    )
    clips = _clips(4, 160)
    model, hist = T.train("gru", clips[:3], cfg, val_clips=clips[3:])
    assert [r["step"] for r in hist["val"]] == [10, 20, 30]
    best = min(hist["val"], key=lambda r: r["mpjpe_0_1"])
    assert hist["val_best"]["step"] == best["step"]
    assert T.Validator(clips[3:])(model)["mpjpe_0_1"] == pytest.approx(best["mpjpe_0_1"], rel=1e-5)
    with pytest.raises(ValueError, match="validation windows"):
        T.Validator([clips[3]][:0] + [D.Clip("short", walker(60), 25.0)])


def test_preview_and_cli_on_track_files(tmp_path):
    from roomcap.forecast.cli import main
    from roomcap.forecast.runtime.preview import preview
    from roomcap.track.trackfile import TrackFile

    sk = get_skeleton("body19")
    paths = []
    for i in range(3):
        xyz = np.stack([walker(90, phase=i), walker(90, start=(2, i), heading_rad=2.0)], 1)
        xyz[40:60, 1] = np.nan  # a gap
        if i == 0:
            xyz[-5:, 1] = np.nan  # person 2 gone at the end: no forecast for it
        T_ = len(xyz)
        tf = TrackFile(
            fps=25.0,
            frame_index=np.arange(T_),
            t_ns=np.arange(T_) * 40_000_000,
            track_id=[3, 8],
            joint_names=sk.joint_names,
            parents=np.asarray(sk.parents),
            xyz_m=xyz,
            confidence=np.ones(xyz.shape[:3]),
            std_m=np.full(xyz.shape[:3], 0.02),
            flags=np.ones(xyz.shape[:3], np.uint8),
        )
        (tmp_path / f"s{i}").mkdir()
        tf.save(tmp_path / f"s{i}" / "tracks.npz")
        paths.append(str(tmp_path / f"s{i}" / "tracks.npz"))
    ck = tmp_path / "gru.pt"
    assert (
        main(
            [
                "train",
                "--model",
                "gru",
                "--data",
                *paths,
                "--set",
                "steps=5",
                "--set",
                "hidden=16",
                "--set",
                "n_obs=20",
                "--set",
                "n_pred=10",
                "--out",
                str(ck),
            ]
        )
        == 0
    )
    fc = preview(paths[0], 0.4, ck)
    assert fc["xyz_m"].shape == (1, 10, 2, 19, 3) and list(fc["track_id"]) == [3, 8]
    assert np.isfinite(fc["xyz_m"][:, :, 0]).all() and np.isnan(fc["xyz_m"][:, :, 1]).all()
    assert (
        main(
            [
                "sample",
                "--checkpoint",
                str(ck),
                "--tracks",
                paths[1],
                "--horizon-s",
                "0.4",
                "--out",
                str(tmp_path / "fc.npz"),
            ]
        )
        == 0
    )
    assert np.load(tmp_path / "fc.npz")["schema"] == "forecast/1"
    out = tmp_path / "eval"
    assert (
        main(
            [
                "eval",
                "--data",
                *paths,
                "--checkpoints",
                str(ck),
                "--fool",
                "--samples",
                "3",
                "--horizon-s",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "| gru |" in (out / "report.md").read_text() and (out / "ndms.png").exists()
    assert (
        main(
            [
                "eval",
                "--social",
                "--data",
                *paths,
                "--checkpoints",
                str(ck),
                "--scenes",
                "2",
                "--horizon-s",
                "1.5",
                "--out",
                str(tmp_path / "soc"),
            ]
        )
        == 0
    )
    assert "SSCP" in (tmp_path / "soc" / "report.md").read_text()


def test_shipped_configs_and_checkpoint_load():
    """Each config TOML holds only what differs from the defaults, and those are the shipped model's."""
    import dataclasses

    from roomcap.core.fileio import load_toml
    from roomcap.forecast.runtime.preview import CHECKPOINT_DIR

    shipped = {
        "gru": "gru_cmuall",
        "intention": "intention_cmuall",
        "social_diffusion": "social_diffusion_1pass_cmuall",
    }
    for kind, spec in MODELS.items():
        table = load_toml(CHECKPOINT_DIR.parent / "configs" / f"{kind}.toml")[kind]
        default = dataclasses.asdict(spec.config())
        assert all(default[k] != v for k, v in table.items()), kind  # only what differs from the defaults
        model, meta = T.load_checkpoint(CHECKPOINT_DIR / f"{shipped[kind]}.pt", skeleton="body19")
        assert CHECKPOINT_DIR.joinpath(f"{shipped[kind]}.pt").stat().st_size < 2_000_000
        assert meta["model"] == kind and meta["fps"] == 25.0
        assert all(getattr(meta["config"], k) == v for k, v in table.items()), kind
    model, meta = T.load_checkpoint(CHECKPOINT_DIR / "social_diffusion_1pass_cmuall.pt", skeleton="body19")
    # per-lag statistics held past the window, one pass over any horizon
    assert model.feat_std.shape == (144, 67) and model.lag_hold and model.anchor == model.n_obs - 1
    assert diffusion_rollout(model, 250) == "one_pass"
    calls = []
    orig = model.sample_window
    model.sample_window = lambda *a, **k: calls.append(k.get("n_frames")) or orig(*a, **k)
    scene = np.stack([walker(32), walker(32, start=(2, 0), heading_rad=2.0)], 1)[None]
    y = forecast_world(model, scene, None, 100, 2)
    assert calls == [144] and y.shape == (1, 2, 100, 2, 19, 3) and np.isfinite(y).all()
    jump = np.linalg.norm(y[0, :, 0] - scene[0, -1], axis=-1).mean()
    assert jump < 0.06  # continues from the observation (a walking step is 0.05 m)
    assert meta["extra"]["val_best"]["select"] == "ndms_2_4"  # picked on the validation split
    model, meta = T.load_checkpoint(CHECKPOINT_DIR / "intention_cmuall.pt", skeleton="body19")
    assert meta["extra"]["val_best"]["select"] == "ndms_2_4"  # picked on the validation split
    assert meta["config"].n_pred == 100
    torch.manual_seed(0)
    y = forecast_world(model, walker(50)[None, :, None], None, 50, n_samples=3)
    assert y.shape == (1, 3, 50, 1, 19, 3) and np.isfinite(y).all()
    assert np.std(y[0, :, -1], axis=0).mean() > 0.002  # samples differ at 2 s


def test_the_registry_names_builds_and_routes_every_trainable_model():
    from roomcap.core.errors import InputError
    from roomcap.forecast.cli import build_parser
    from roomcap.forecast.runtime.registry import build_model, forecasts_the_scene, spec, spec_of

    assert tuple(MODELS) == ("gru", "intention", "social_diffusion")
    for name, s in MODELS.items():
        m = build_model(name, s.config(), 19)
        assert spec_of(m) is s and m.n_obs == s.config().n_obs
        assert forecasts_the_scene(m) == (name == "social_diffusion")
        assert s.intentions == (name == "intention")
    assert spec_of(ZeroVelocity()) is None and not forecasts_the_scene(ConstantVelocity())
    with pytest.raises(InputError, match="unknown model 'lstm'; trainable models"):
        spec("lstm")
    train = build_parser()._subparsers._group_actions[0].choices["train"]
    assert next(a for a in train._actions if a.dest == "model").choices == tuple(MODELS)


def test_the_runtime_imports_without_torch_and_without_the_lab():
    """What the pipeline and users' code import to load a checkpoint and forecast a track: no torch until a
    model is built or a file read, and nothing of the lab (training, datasets, benchmarks)."""
    import subprocess
    import sys

    code = (
        "import sys; import roomcap.forecast.runtime, roomcap.forecast.runtime.preview, "
        "roomcap.forecast.runtime.registry, roomcap.forecast.runtime.checkpoint, "
        "roomcap.forecast.runtime.cards, roomcap.forecast.runtime.baselines, "
        "roomcap.forecast.runtime.normalise, roomcap.pipeline.stages; "
        "print('torch' in sys.modules, any(m.startswith('roomcap.forecast.lab') for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False False"


def test_held_lag_statistics_generate_past_the_window_and_continue_a_shared_stats_model():
    """lag_hold: per-lag statistics (fine near the observation) held at the last lag past the training window,
    so one pass covers any horizon; continuing a per-channel-statistics model refits the statistics."""
    base = {"channels": 16, "T": 50, "n_frames": 32, "n_obs": 16, "steps": 2, "batch": 4, "sample_steps": 3}
    shared, _ = T.train(
        "social_diffusion", _clips(3, 100), T.config_from_dict("social_diffusion", {**base, "lag_stats": 0})
    )
    cfg = T.config_from_dict("social_diffusion", {**base, "lag_hold": 1})
    held, _ = T.train("social_diffusion", _clips(3, 100), cfg, init=shared.state_dict())
    assert held.feat_std.shape == (32, 67) and held.lag_hold
    assert not torch.equal(held.inp.weight, shared.inp.weight)  # the weights continued and trained on
    mean, std = held._stats(50)
    assert (
        mean.shape == (50, 67)
        and torch.equal(std[40], held.feat_std[-1])
        and torch.equal(std[:32], held.feat_std)
    )
    i = 19 * 3  # root offsets: the spread grows with the lag, so early frames get a finer code than shared
    assert held.feat_std[17, i : i + 2].max() < 0.5 * held.feat_std[-1, i : i + 2].min()
    assert diffusion_rollout(held, 100) == "one_pass"
    scene = np.stack([walker(16), walker(16, start=(2, 0))], 1)[None]
    y = forecast_world(held, scene, None, 100, n_samples=2)
    assert y.shape == (1, 2, 100, 2, 19, 3) and np.isfinite(y).all()
    with pytest.raises(ValueError, match="per-lag statistics cover 32"):
        T.build_model("social_diffusion", T.config_from_dict("social_diffusion", base), 19)._stats(40)
