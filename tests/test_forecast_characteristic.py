"""Characteristic 3D pose forecasting (Diller ch. 3): annotator, model, sampler, refinement, checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roomcap.core.errors import FormatError
from roomcap.forecast.lab import characteristic as C
from roomcap.forecast.lab.characteristic.network import refine_pose, target_heatmap
from roomcap.keypoints.skeletons import get_skeleton

torch.set_num_threads(1)
SK = get_skeleton("body19")
NAMES = SK.joint_names
J = SK.n_joints
FPS = 25.0
TINY = C.CharConfig(
    hidden=16, dim=16, heads=2, grid=8, channels=4, batch=4, steps=3, det_steps=3, val_every=0
)

# a standing body19 pose in the canonical frame (left on -x, right on +x, z up), metres
STAND = {
    "nose": (0, -0.1, 1.65), "left_eye": (-0.03, -0.08, 1.68), "right_eye": (0.03, -0.08, 1.68),
    "left_ear": (-0.08, 0, 1.66), "right_ear": (0.08, 0, 1.66), "left_shoulder": (-0.2, 0, 1.45),
    "right_shoulder": (0.2, 0, 1.45), "left_elbow": (-0.25, 0, 1.15), "right_elbow": (0.25, 0, 1.15),
    "left_wrist": (-0.27, 0, 0.9), "right_wrist": (0.27, 0, 0.9), "left_hip": (-0.1, 0, 0.95),
    "right_hip": (0.1, 0, 0.95), "left_knee": (-0.1, 0, 0.5), "right_knee": (0.1, 0, 0.5),
    "left_ankle": (-0.1, 0, 0.08), "right_ankle": (0.1, 0, 0.08), "pelvis": (0, 0, 0.95), "neck": (0, 0, 1.5),
}  # fmt: skip
POSE = np.array([STAND[n] for n in NAMES], np.float64)


def _smoothstep(n):
    t = np.linspace(0, 1, n)
    return t * t * (3 - 2 * t)


def synthetic_clip(seed: int = 0):
    """Rest, then three actions (right hand reach, left foot kick, left hand raise), each an eased move out,
    a short
    hold and an eased return, while the whole body walks and turns. -> xyz (T,J,3), the known cusp frames."""
    moves = [
        ("right_wrist", (0, -0.5, 0.4)),
        ("left_ankle", (0, -0.45, 0.25)),
        ("left_wrist", (-0.2, 0, 0.8)),
    ]
    frames, cusps = [np.zeros((20, J, 3))], []
    for name, d in moves:
        j = NAMES.index(name)
        out = np.zeros((20, J, 3))
        out[:, j] = _smoothstep(20)[:, None] * np.asarray(d)
        hold = np.repeat(out[-1:], 5, 0)
        back = out[::-1]
        t0 = sum(len(f) for f in frames)
        cusps.append(t0 + 20 + 2)  # middle of the hold
        frames += [out, hold, back, np.zeros((25, J, 3))]
    disp = np.concatenate(frames)
    T = len(disp)
    x = POSE[None] + disp
    heading = np.linspace(0, 1.2, T)  # turn while walking forward
    c, s = np.cos(heading), np.sin(heading)
    R = np.stack(
        [np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1), np.stack([0 * c, 0 * c, 1 + 0 * c], -1)],
        -2,
    )
    x = (
        np.einsum("tij,tkj->tki", R, x)
        + np.stack([np.linspace(0, 2, T), np.linspace(0, 1, T), 0 * c], -1)[:, None]
    )
    x += np.random.default_rng(seed).normal(0, 0.003, x.shape)  # mocap jitter
    return x.astype(np.float32), np.asarray(cusps)


# ----------------------------------------------------------------------------- annotator


def test_annotator_finds_the_known_cusps_and_nothing_else():
    x, cusps = synthetic_clip()
    labels = C.annotate(x, NAMES, FPS)
    assert len(labels) == len(cusps), (labels, cusps)
    assert np.abs(labels - cusps).max() <= 3, (labels, cusps)


def test_annotator_ignores_small_motion_and_rejects_nan():
    x, _ = synthetic_clip()
    rest = np.repeat(x[:1], 120, 0) + np.random.default_rng(1).normal(0, 0.01, (120, J, 3)).astype(np.float32)
    assert len(C.annotate(rest, NAMES, FPS)) == 0  # jitter is no action
    x[5, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        C.annotate(x, NAMES, FPS)


def test_segments_and_starts_follow_the_protocol():
    x, _ = synthetic_clip()
    item = C.Labelled("syn", x, np.array([5, 40, 60, 65]))
    segs = C.segments([item], n_obs=10)
    # label 5 is too close to the clip start, 65 too close to 60: each observation needs N frames
    assert segs.tolist() == [[0, 5, 40], [0, 40, 60]]
    rows = C.eval_starts(segs, 10, 5)
    assert rows[:5, 1].tolist() == [5, 11, 18, 24, 30]  # evenly from the segment start to N frames before
    obs, tgt = C.make_pairs([item], rows, 10, NAMES)
    lh, rh = NAMES.index("left_hip"), NAMES.index("right_hip")
    assert obs.shape == (10, 10, J, 3) and tgt.shape == (10, J, 3)
    np.testing.assert_allclose(0.5 * (tgt[:, lh] + tgt[:, rh]), 0, atol=1e-5)  # hip-centred target
    np.testing.assert_allclose(0.5 * (obs[:, -1, lh] + obs[:, -1, rh]), 0, atol=1e-5)  # eq. 3.8
    np.testing.assert_allclose(obs[:, -1, rh, 1], 0, atol=1e-5)  # hip vector on +x (rotation about z)
    assert (obs[:, -1, rh, 0] > 0).all()


# ----------------------------------------------------------------------------- model


def test_heatmap_target_peaks_at_the_point():
    y = torch.tensor([[0.3, -0.2, 0.55]])
    h = target_heatmap(y, 16, 2.0)
    i = np.unravel_index(int(h.argmax()), h.shape[1:])
    centre = -1 + (np.asarray(i) + 0.5) * 2 / 16
    assert np.abs(centre - y.numpy()[0]).max() <= 1 / 16 + 1e-6
    assert float(h.max()) <= 1 and (h > 0).sum() <= 125  # kernel size 5


def test_model_shapes_loss_and_autoregressive_order():
    torch.manual_seed(0)
    net, det = C.build_models(TINY)
    obs = torch.randn(3, 10, J, 3) * 0.3
    tgt = torch.randn(3, J, 3) * 0.3
    terms = net.loss(obs, tgt, n_rest=2)
    assert torch.isfinite(terms["loss"]) and terms["loss"].requires_grad
    calls = []
    orig = net._features

    def spy(enc, query, prior_xyz=None, prior_ids=None):
        calls.append((list(query), None if prior_ids is None else list(prior_ids)))
        return orig(enc, query, prior_xyz, prior_ids)

    net._features = spy
    s = net.sample(obs, k=6, generator=torch.Generator().manual_seed(0), refine=False)
    rw, lw = NAMES.index("right_wrist"), NAMES.index("left_wrist")
    assert s.shape == (3, 6, J, 3) and torch.isfinite(s).all()
    assert calls[0] == ([rw], None)  # right wrist first, unconditioned
    assert calls[1] == ([lw], [rw])  # then the left wrist given the right
    assert calls[2][1] == [rw, lw] and sorted(calls[2][0] + [rw, lw]) == list(range(J))
    assert (s[:, 1:] - s[:, :1]).abs().amax((-1, -2, -3)).min() > 0  # the k hypotheses differ
    assert float(s.abs().max()) <= TINY.span / 2 + 0.5 * TINY.span / TINY.grid + 1e-5  # grid + offset
    # the prior joint is an attention node: moving the sampled right wrist changes the left wrist's feature
    enc = net.backbone.encode(obs)
    f1 = orig(enc, [lw], torch.zeros(3, 1, 3), [rw])
    f2 = orig(enc, [lw], torch.full((3, 1, 3), 0.5), [rw])
    assert (f1 - f2).abs().max() > 1e-6
    assert det.sample(obs, k=4).shape == (3, 4, J, 3)


@pytest.mark.slow
def test_refinement_restores_bone_lengths():
    torch.manual_seed(0)
    bones = torch.tensor([(p, j) for j, p in enumerate(SK.parents) if p >= 0])
    true = torch.from_numpy(POSE - POSE[NAMES.index("pelvis")]).float()[None]
    noisy = true + torch.randn_like(true) * 0.05
    heat = torch.zeros(1, J, 8, 8, 8)
    rw, lw = NAMES.index("right_wrist"), NAMES.index("left_wrist")
    out = refine_pose(noisy, heat, true, true, (rw, lw), bones, 2.0, iters=150)

    def bone_err(x):
        return float(
            (
                (x[:, bones[:, 1]] - x[:, bones[:, 0]]).norm(dim=-1)
                - (true[:, bones[:, 1]] - true[:, bones[:, 0]]).norm(dim=-1)
            )
            .abs()
            .mean()
        )

    assert bone_err(out) < 0.5 * bone_err(noisy)


@pytest.mark.slow
def test_training_runs_on_a_synthetic_clip():
    x, _ = synthetic_clip()
    items = [C.Labelled("syn", x, C.annotate(x, NAMES, FPS))]
    data = C.CharData(items, [], items, "body19", {})
    net, det, avg, hist = C.train(data, TINY)
    assert avg.shape == (J, 3) and hist["heatmap"]["steps_done"] == 3
    assert np.isfinite(hist["heatmap"]["loss"]).all() and np.isfinite(hist["deterministic"]["loss"]).all()
    res = C.evaluate(net, det, avg, items, TINY, k=3, refine=False)
    assert set(res["methods"]) == {"ours", "deterministic", "zero_velocity", "average_train_pose"}
    assert res["n_windows"] == 5 * res["n_labels"] and res["methods"]["ours"]["diversity"] > 0


# ----------------------------------------------------------------------------- checkpoints


def test_checkpoint_round_trip_and_skeleton_mismatch(tmp_path):
    torch.manual_seed(0)
    net, det = C.build_models(TINY)
    avg = np.random.default_rng(0).normal(size=(J, 3)).astype(np.float32)
    path = tmp_path / "c.pt"
    C.save_checkpoint(path, net, det, TINY, avg)
    net2, det2, meta = C.load_checkpoint(path, skeleton="body19")
    assert meta["config"] == TINY and meta["skeleton"] == "body19" and "eq. 3.8" in meta["normalisation"]
    np.testing.assert_allclose(meta["avg_pose"], avg)
    obs = torch.randn(2, 10, J, 3) * 0.3
    a = net.sample(obs, 4, refine=False, generator=torch.Generator().manual_seed(1))
    b = net2.sample(obs, 4, refine=False, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(a, b)
    with pytest.raises(FormatError, match="smpl29"):
        C.load_checkpoint(path, skeleton="smpl29")
    bad = tmp_path / "bad.pt"
    torch.save({"schema": "forecast-checkpoint/1"}, bad)
    with pytest.raises(FormatError, match="schema"):
        C.load_checkpoint(bad)


@pytest.mark.slow
def test_shipped_checkpoint_beats_the_average_pose_on_held_out_clips():
    from conftest import need_shared

    need_shared("data", "motion")
    if not C.SHIPPED.exists():
        pytest.skip(f"no shipped checkpoint at {C.SHIPPED}")
    net, det, meta = C.load_checkpoint(C.SHIPPED, skeleton="body19")
    data = C.load_cmu_labelled(meta["fps"])
    res = C.evaluate(net, det, meta["avg_pose"], data.test, meta["config"], max_windows=20, refine=True)
    m = res["methods"]
    assert m["ours"]["mpjpe"] < m["average_train_pose"]["mpjpe"], m
    assert m["ours"]["diversity"] > 0
