"""The CMU 8-action benchmark protocol (forecast eval --protocol cmu8): the reference's windows, joints and
averaging on a tiny synthetic benchmark folder, the DCT + MLP, samples.npz, and bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from roomcap.core.errors import InputError, RoomcapError
from roomcap.forecast.lab import benchmark_cmu8 as B
from roomcap.forecast.lab import benchmark_cmu8_train as BT
from roomcap.forecast.lab import cmu_more as C
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.protocol import RESULTS_SCHEMA, render
from roomcap.forecast.lab.toy import walker
from roomcap.forecast.runtime.checkpoint import read_checkpoint
from tests.conftest import need_shared


def _write_action(root, split, action, k, n_frames, rng):
    """A synthetic benchmark file: 117 values a line, smooth exp-maps on the joints that move."""
    t = np.arange(n_frames)[:, None] / 120.0
    a = np.zeros((n_frames, 117))
    cols = 3 + 3 * np.array([2, 3, 4, 9, 10, 14, 15, 21, 22, 30, 31])  # hips, knees, spine, arms (exp-map x)
    a[:, cols] = 0.4 * np.sin(2 * np.pi * (0.8 + rng.random(len(cols))) * t + rng.random(len(cols)) * 6)
    d = root / split / action
    d.mkdir(parents=True, exist_ok=True)
    np.savetxt(d / f"{action}_{k}.txt", a, delimiter=",", fmt="%.6f")


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    """walking and soccer with a test file each, jumping with train files only; the rest missing."""
    root = tmp_path_factory.mktemp("bench") / "benchmark-cmu8"
    rng = np.random.default_rng(0)
    for a in ("walking", "soccer"):
        _write_action(root, "test", a, 1, 400, rng)
        for k in (1, 2):
            _write_action(root, "train", a, k, 300, rng)
    _write_action(root, "train", "jumping", 1, 300, rng)
    return root


def test_windows_joints_and_scoring_follow_the_reference():
    # a fresh RandomState(1234567890) per file, randint(0, F - 75), 8 draws
    rng = np.random.RandomState(1234567890)
    assert B.window_starts(300).tolist() == [rng.randint(0, 225) for _ in range(8)]
    assert B.window_starts(300).tolist() == B.window_starts(300).tolist()
    assert len(B.JOINTS_USED) == 25 and B.HORIZON_FRAMES == (1, 3, 7, 9, 13, 24)
    gt = np.random.default_rng(1).normal(size=(3, 25, 38, 3))
    for j, k in B.JOINTS_EQUAL.items():  # as in the data: these points sit on their partner
        gt[..., j, :] = gt[..., k, :]
    full = B.complete(gt[..., list(B.JOINTS_USED), :] + 1.0, gt)
    assert np.allclose(full[..., 0, :], gt[..., 0, :])  # fixed points from the truth
    assert np.allclose(full[..., 16, :], full[..., 15, :])  # coinciding points from the partner's forecast
    e = B.mpjpe_mm(full, gt)  # 25 points off by sqrt(3) units, their 7 copies too, the 6 fixed ones exact
    assert e.shape == (3, 25)
    assert np.allclose(e, B.MM_PER_UNIT * np.sqrt(3) * 32 / 38)
    assert B.mpjpe_mm(gt, gt).max() == 0
    # the DCT matrix is orthonormal (the reference's get_dct_matrix)
    d = B.dct_matrix(50)
    assert np.allclose(d @ d.T, np.eye(50), atol=1e-10)


def test_protocol_on_a_tiny_benchmark(tiny_root, tmp_path):
    cfg = B.MlpConfig(steps=2, batch=8, val_every=1, n_blocks=2)
    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    assert [f.name for f in va] == ["soccer_2.txt", "walking_2.txt"]  # the last file of each 2-file action
    model, hist = BT.train_mlp(tr, va, cfg)
    ck = tmp_path / "mlp.pt"
    B.save_mlp(ck, model, cfg, {"train_files": [f.name for f in tr]})
    assert B.is_cmu8_checkpoint(ck)
    res = B.evaluate(tiny_root, mlp_checkpoints=[ck], samples_dir=tmp_path / "s", n_windows=2)
    assert res["protocol"] == "cmu8" and res["horizons_ms"] == [80, 160, 320, 400, 560, 1000]
    assert res["actions"] == ["soccer", "walking"]
    assert "jumping" in res["actions_missing"] and "test/jumping/jumping_1.txt" in res["files_missing"]
    assert "test/basketball_signal and test/directing_traffic are missing" in res["note"]
    for name in ("zero_velocity", "mlp"):
        r = res["models"][name]
        pa = [r["per_action"][a]["mpjpe_mm"] for a in res["actions"]]
        assert np.allclose(r["mpjpe_mm"], np.mean(pa, 0))  # the average over the scored actions
        assert len(r["mpjpe_mm"]) == 6 and all(v > 0 for v in r["mpjpe_mm"])
    assert res["models"]["zero_velocity@body19"]["variant"] == "body19"
    pub = res["published"]["MSR-GCN (Dang et al. 2021)"]
    assert pub["source"] and len(pub["mpjpe_mm"]) == 6 and len(pub["average_same_actions"]) == 6
    # samples: rescoring the saved forecasts gives the reported numbers
    z = np.load(tmp_path / "s" / "samples_mlp.npz")
    assert z["pred"].shape == (4, 1, 25, 38, 3) and z["obs"].shape == (4, 50, 38, 3)
    assert z["gt"].shape == (4, 25, 38, 3) and z["fps"] == 60.0 and len(z["joint_names"]) == 38
    assert list(z["activity"]) == ["soccer"] * 2 + ["walking"] * 2 and str(z["model"]) == "mlp"
    assert list(z["clip"]) == ["soccer_1"] * 2 + ["walking_1"] * 2  # the test file of each window
    e = np.linalg.norm(z["pred"][:, 0] - z["gt"], axis=-1).mean(-1) * z["protocol_mm_per_m"]
    assert np.allclose(e[:, list(B.HORIZON_FRAMES)].mean(0), res["models"]["mlp"]["mpjpe_mm"], rtol=1e-4)
    md = render(res)
    assert res["schema"] == RESULTS_SCHEMA and res["tables"][0]["columns"][0] == "model"
    assert "Exact protocol" in md and "missing" in md and "MSR-GCN" in md


def test_cli_cmu8_bad_input(tiny_root, tmp_path, capsys):
    from roomcap.forecast.cli import main

    out = tmp_path / "o"
    assert main(["eval", "--protocol", "cmu9", "--out", str(out)]) == 2
    assert "unknown protocol 'cmu9'; choose one of cmu, cmu8, cmu8-all, hik" in capsys.readouterr().err
    assert main(["eval", "--protocol", "cmu8", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert "no train/ or test/ folder" in capsys.readouterr().err
    # a folder with files missing: they are named and the rest is scored
    assert main(["eval", "--protocol", "cmu8", str(tiny_root), "--checkpoints", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert (
        "not scored: basketball, basketball_signal, directing_traffic, jumping, running, washwindow" in text
    )
    res = json.loads((out / "results.json").read_text())
    assert set(res["models"]) == {"zero_velocity", "zero_velocity@body19"}
    assert "test/running/running_1.txt" in res["files_missing"]


def test_all_windows_protocol_on_a_tiny_benchmark(tiny_root, tmp_path, capsys):
    """cmu8-all (MSR-GCN's / PGBIG's 'all'): every 10 + 25-frame window, stride 1; the model's 50-frame
    history from the file, padded with its first frame before the file's start."""
    from roomcap.forecast.cli import main

    seq = np.arange(60.0)[:, None, None] * np.ones((1, 38, 3))
    starts, w, full = B.all_windows(seq)
    assert starts.tolist() == list(range(26)) and w.shape == (26, 75, 38, 3)
    assert np.allclose(w[:, B.N_OBS - B.ALL_OBS :, 0, 0], starts[:, None] + np.arange(35))  # the 35 frames
    assert np.allclose(w[0, : B.N_OBS - B.ALL_OBS], 0) and not full.any()  # padded with frame 0
    long = np.arange(100.0)[:, None, None] * np.ones((1, 38, 3))
    s2, w2, full2 = B.all_windows(long)
    assert full2.tolist() == [s >= 40 for s in s2] and np.allclose(w2[40, :, 0, 0], np.arange(75))
    with pytest.raises(InputError, match="at least 35 frames"):
        B.all_windows(seq[:34])
    res = B.evaluate(tiny_root, samples_dir=tmp_path / "s", windows="all")
    assert res["protocol"] == "cmu8-all" and res["title"].endswith("(protocol cmu8-all)")
    n = len(B.sequence(tiny_root / "test" / "walking" / "walking_1.txt")) - 35 + 1
    assert res["n_windows"] == {"soccer": n, "walking": n}
    assert res["n_padded"] == {"soccer": 40, "walking": 40}
    assert set(res["models"]) == {"zero_velocity"}  # no body19 entries on this protocol
    z = res["models"]["zero_velocity"]
    assert len(z["mpjpe_mm_full_history"]) == 6 and z["mpjpe_mm_full_history"] != z["mpjpe_mm"]
    pub = res["published"]
    assert pub["PGBIG (Ma et al. 2022)"]["same_windows"] and not pub["LTD (Mao et al. 2019)"]["same_windows"]
    pg = pub["PGBIG (Ma et al. 2022)"]["average_same_actions"]
    assert pg[-1] == pytest.approx((99.98 + 33.93) / 2, abs=0.01)
    # rescoring the saved forecasts gives the reported numbers, over every window
    zs = np.load(tmp_path / "s" / "samples_zero_velocity.npz")
    assert str(zs["protocol"]) == "cmu8-all" and len(zs["gt"]) == 2 * n
    e = np.linalg.norm(zs["pred"][:, 0] - zs["gt"], axis=-1).mean(-1) * zs["protocol_mm_per_m"]
    per = [e[zs["activity"] == a][:, list(B.HORIZON_FRAMES)].mean(0) for a in ("soccer", "walking")]
    assert np.allclose(np.mean(per, 0), z["mpjpe_mm"], rtol=1e-4)
    assert "other windows" in render(res) and "All windows (38 points)" in render(res)
    # the command line: the 38-point models only
    out = tmp_path / "o"
    assert main(["eval", "--protocol", "cmu8-all", str(tiny_root), "--checkpoints", "--out", str(out)]) == 0
    assert "every window of 10 + 25 frames" in capsys.readouterr().out
    with pytest.raises(InputError, match="38-point models only"):
        B.evaluate(tiny_root, body19_checkpoints=["gru_cmuall.pt"], windows="all")


def test_eval_single_writes_samples(tmp_path):
    from roomcap.forecast.lab.data import Clip

    clips = [Clip(f"walk{i}", walker(150, phase=i, heading_rad=i), 25.0) for i in range(3)]
    models = {"zero": T.baseline("zero"), "real": E.Real()}
    torch.manual_seed(0)
    E.evaluate_single(
        models, clips, n_obs=25, n_pred=50, n_samples=2, stride=25, n_boot=20, samples_dir=tmp_path,
        activities={c.name: "walk" for c in clips},
    )  # fmt: skip
    z = np.load(tmp_path / "samples_zero.npz")
    N = len(z["activity"])
    assert N > 0 and z["pred"].shape == (N, 1, 50, 19, 3) and z["obs"].shape == (N, 25, 19, 3)
    assert z["gt"].shape == (N, 50, 19, 3) and float(z["fps"]) == 25.0 and str(z["model"]) == "zero"
    assert np.allclose(z["pred"][:, 0, -1], z["obs"][:, -1], atol=1e-5)  # zero velocity: the last pose
    # the clip of every window: its observed frames are that clip's frames (and no other clip's)
    by_name = {c.name: c.xyz_m[:, 0] for c in clips}
    assert set(z["clip"]) == set(by_name)
    for o, c in zip(z["obs"], z["clip"], strict=True):
        hits = {n for n, x in by_name.items() if (np.abs(x - o[0]).max((1, 2)) < 1e-5).any()}
        assert hits == {str(c)}
    r = np.load(tmp_path / "samples_real.npz")
    assert np.allclose(r["pred"][:, 0], r["gt"])


def test_shared_test_windows():
    need_shared("data", "motion", "cmu-more", "benchmark-cmu8", "test", "walking", "walking_1.txt")
    ts = B.test_set(C.benchmark_files(), actions=["walking", "basketball_signal"])
    assert ts.windows["walking"].shape == (8, 75, 38, 3)
    assert ts.actions_missing == ["basketball_signal"]
    seq = B.sequence(ts.files["walking"][0])
    s = B.window_starts(len(seq))
    assert np.allclose(ts.windows["walking"][0], seq[s[0] : s[0] + 75])


def test_eval_without_checkpoints_scores_the_shipped_ones(tiny_root, tmp_path, monkeypatch):
    from roomcap.forecast import cli
    from roomcap.forecast.runtime.preview import shipped_checkpoints

    seen = {}
    real_evaluate = B.evaluate

    def fake_evaluate(root, mlp_checkpoints, body19_checkpoints, **kw):
        seen.update(mlp=mlp_checkpoints, b19=body19_checkpoints)
        return real_evaluate(root, n_windows=1)

    monkeypatch.setattr(B, "evaluate", fake_evaluate)
    assert cli.main(["eval", "--protocol", "cmu8", str(tiny_root), "--out", str(tmp_path / "o")]) == 0
    shipped = shipped_checkpoints()
    assert any(p.endswith("gru_cmuall.pt") for p in shipped)
    assert not any(n in p for p in shipped for n in ("characteristic", "behaviour", "cmu8_"))
    assert seen["b19"] == shipped
    assert seen["mlp"] == ([str(B.SHIPPED_MLP)] if B.SHIPPED_MLP.is_file() else [])
    # cmu8-all: the same pick (it won in both layouts), no body19 model
    assert cli.main(["eval", "--protocol", "cmu8-all", str(tiny_root), "--out", str(tmp_path / "a")]) == 0
    assert seen["mlp"] == [str(B.SHIPPED_MLP)] and seen["b19"] == [] and B.SHIPPED_MLP.is_file()


def test_mirror_swaps_sides_and_is_an_involution():
    idx = BT.mirror_index()
    used = list(B.JOINTS_USED)
    assert sorted(idx.tolist()) == list(range(25)) and (idx[idx] == np.arange(25)).all()
    assert idx[used.index(3)] == used.index(9)  # left knee <-> right knee
    assert idx[used.index(14)] == used.index(14)  # the spine stays
    b = torch.randn(2, 5, 25, 3)
    m = BT._mirror(b, torch.tensor([True, False]), torch.from_numpy(idx))
    assert torch.equal(m[1], b[1]) and torch.allclose(m[0, :, used.index(3), 0], -b[0, :, used.index(9), 0])
    assert torch.allclose(BT._mirror(m, torch.tensor([True, True]), torch.from_numpy(idx))[0], b[0])


def test_shipped_dct_mlp_checkpoints():
    ck = B.SHIPPED_MLP
    if not ck.exists():
        pytest.skip(f"no shipped cmu8 checkpoint {ck.name}")
    assert ck.stat().st_size < 4_000_000  # measured 216 KB for one model, 3.6 MB for the shipped 10
    model, blob = B.load_mlp(ck)
    trains = blob["extra"]["member_train"] if isinstance(model, B.DctMlpEnsemble) else [blob["extra"]]
    for t in trains:
        assert t["best"]["step"] > 0 and t["val_files"]  # every model picked on validation
        assert not any("test" in f for f in t["train_files"])
        assert not set(t["train_files"]) & set(t["val_files"])
    obs = np.cumsum(np.random.default_rng(0).normal(0, 0.01, (2, 50, 38, 3)), 1)
    y = B.mlp_forecast(model, obs)
    assert y.shape == (2, 25, 38, 3) and np.isfinite(y).all()
    assert np.abs(y[:, 0] - obs[:, -1]).max() < 1.0  # continues from the last observed pose (ASF units)


def test_reverse_plays_chosen_windows_backwards():
    b = torch.randn(3, 75, 25, 3)
    r = B.reverse_windows(b, torch.tensor([True, False, True]))
    assert torch.equal(r[1], b[1])
    assert torch.equal(r[0, 0], b[0, -1]) and torch.equal(r[2, 50], b[2, 24])
    assert torch.equal(B.reverse_windows(r, torch.tensor([True, False, True])), b)


def _random_mlp(seed: int) -> tuple[B.DctMlp, B.MlpConfig]:
    cfg = B.MlpConfig(n_blocks=2, seed=seed)
    torch.manual_seed(seed)
    m = B.DctMlp(25, cfg)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))  # away from the near-identity initialisation
    return m.eval(), cfg


def test_a_ten_frame_model_is_rolled_out_to_the_protocols_25_frames():
    """siMLPe's long-term forecast: a model of 10 frames a pass forecasts 25 by feeding its own frames back;
    the first 10 are its one pass, the next 10 its pass on the observation moved on by those 10."""
    cfg = B.MlpConfig(n_blocks=2, n_pred=10, seed=3)
    torch.manual_seed(3)
    m = B.DctMlp(25, cfg).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))
    obs = np.cumsum(np.random.default_rng(1).normal(0, 0.05, (3, 50, 38, 3)), 1)
    y = B.mlp_forecast(m, obs)
    assert y.shape == (3, 25, 38, 3) and np.isfinite(y).all()
    used = list(B.JOINTS_USED)
    o = torch.from_numpy(obs[:, :, used].astype(np.float32))
    with torch.no_grad():
        first = m(o)
        second = m(torch.cat([o, first], 1)[:, -50:])
    assert np.allclose(y[:, :10][:, :, used], first.numpy(), atol=1e-5)
    assert np.allclose(y[:, 10:20][:, :, used], second.numpy(), atol=1e-5)
    assert np.abs(y[:, 10:20][:, :, used] - first.numpy()).max() > 1e-3  # not the first pass repeated


def test_pad_start_pads_the_oldest_history_as_cmu8_all_does(tiny_root, tmp_path, capsys):
    """`--pad-start`: a training window's oldest frames are replaced by its first kept frame (what cmu8-all
    gives a model near a file's start); the newest 10 observed frames and the future stay as they were."""
    b = torch.arange(75.0)[None, :, None, None].expand(3, 75, 25, 3).clone()
    out = BT._pad_start(b, torch.tensor([0, 1, 40]))
    assert torch.equal(out[0], b[0]) and torch.equal(out[1, 1:], b[1, 1:]) and (out[1, 0] == 1).all()
    assert (out[2, :41] == 40).all() and torch.equal(out[2, 41:], b[2, 41:])
    from roomcap.forecast.cli import main

    ck = tmp_path / "p.pt"
    args = ["cmu8", "train", str(tiny_root), "--out", str(ck), *"--steps 2 --blocks 1 --n-pred 10".split()]
    assert main([*args, "--pad-start", "0.5"]) == 0
    assert B.load_mlp(ck)[1]["config"]["members"][0]["pad_start"] == 0.5
    # --all-files: the validation files are trained on too, and the last step is kept
    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    assert main([*args, "--all-files", "--angles"]) == 0
    extra = read_checkpoint(ck)["extra"]
    assert sorted(extra["train_files"]) == sorted(f.name for f in tr + va) and not extra["val_files"]
    assert extra["best"]["step"] == 2 and [c["step"] for c in extra["curve"]] == [2]
    ens = ["cmu8", "ensemble", str(ck), str(ck), "--data", str(tiny_root), "--out", str(tmp_path / "e.pt")]
    assert main(ens) == 0 and "not held out" in capsys.readouterr().out


def test_width_and_frame_loss_options(tiny_root, tmp_path):
    """`--width`: the channels between the spatial layers (0 keeps siMLPe's, one per input value);
    `--frame-loss`: a frame's error is the norm over all its values (LTD's angle loss), not the mean of its
    points' norms. Both are kept in the checkpoint and rebuilt from it."""
    fut = torch.zeros(1, 2, 2, 3)
    pred = fut.clone()
    pred[:, :, 0, 0], pred[:, :, 1, 0] = 3.0, 4.0  # every frame: points off by 3 and 4, no change between
    assert float(B.window_loss(pred, fut)) == pytest.approx(3.5)
    assert float(B.window_loss(pred, fut, per_frame=True)) == pytest.approx(5.0)
    assert B.DctMlp(25, B.MlpConfig(n_blocks=1)).fc_in.out_features == 75
    from roomcap.forecast.cli import main

    ck = tmp_path / "w.pt"
    args = ["cmu8", "train", str(tiny_root), "--out", str(ck), *"--steps 2 --blocks 1 --n-pred 10".split()]
    assert main([*args, "--width", "32", "--frame-loss"]) == 0
    m, blob = B.load_mlp(ck)
    assert blob["config"]["members"][0]["frame_loss"] and m.fc_in.out_features == 32
    assert main([*args, "--angles", "--model", "intention", "--width", "32"]) == 2


def test_spatial_mix_option(tiny_root, tmp_path):
    """`--spatial-mix`: every block gains a linear layer over the channels (with its LayerNorm), kept in the
    checkpoint and rebuilt from it; without it the weights' names are those of the checkpoints before."""
    from roomcap.forecast.cli import main

    plain = set(B.DctMlp(25, B.MlpConfig(n_blocks=2)).state_dict())
    mixed = set(B.DctMlp(25, B.MlpConfig(n_blocks=2, spatial_mix=True)).state_dict())
    added = {f"blocks.{i}.{n}.{w}" for i in range(2) for n in ("fc_s", "norm_s") for w in ("weight", "bias")}
    assert not any(".fc_s." in k or ".norm_s." in k for k in plain) and mixed - plain == added
    ck = tmp_path / "m.pt"
    args = ["cmu8", "train", str(tiny_root), "--out", str(ck), *"--steps 2 --blocks 1 --n-pred 10".split()]
    assert main([*args, "--spatial-mix"]) == 0
    m, blob = B.load_mlp(ck)
    assert blob["config"]["members"][0]["spatial_mix"] and m.blocks[0].fc_s.weight.shape == (75, 75)
    assert main([*args, "--angles", "--model", "intention", "--spatial-mix"]) == 2


def test_pad_last_forecasts_past_the_observation_in_one_pass(tiny_root, tmp_path):
    """`--pad-last`: 10 frames observed, padded with the last one, 25 forecast in one pass (LTD's and PGBIG's
    input): the DCT spans all 35 frames, the checkpoint rebuilds it, and without it n_pred > n_obs is refused
    as before."""
    from roomcap.forecast.cli import main

    with pytest.raises(InputError, match="unless --pad-last"):
        B.DctMlp(25, B.MlpConfig(n_obs=10, n_pred=25))
    m = B.DctMlp(25, B.MlpConfig(n_obs=10, n_pred=25, n_blocks=2, pad_last=True))
    assert m.dct.shape == (35, 35) and m.blocks[0].fc.weight.shape == (35, 35)
    assert m(torch.randn(2, 10, 25, 3)).shape == (2, 25, 25, 3)
    ck = tmp_path / "p.pt"
    args = ["cmu8", "train", str(tiny_root), "--out", str(ck), *"--steps 2 --blocks 1".split()]
    assert main([*args, "--n-obs", "10", "--n-pred", "25", "--pad-last"]) == 0
    m, blob = B.load_mlp(ck)
    assert blob["config"]["members"][0]["pad_last"] and (m.n_obs, m.n_pred) == (10, 25)
    obs = np.cumsum(np.random.default_rng(0).normal(0, 0.01, (2, 50, 38, 3)), 1)
    assert B.mlp_forecast(m, obs).shape == (2, 25, 38, 3)
    assert main([*args, "--angles", "--model", "intention", "--pad-last"]) == 2


def test_validate_scores_a_ten_frame_history_model_on_the_all_windows_layout(tiny_root, tmp_path, capsys):
    """`forecast cmu8 validate --windows all`: every start of each validation file, the history padded as
    cmu8-all pads the test files; a model observing 10 frames forecasts from the newest 10 of them."""
    from roomcap.forecast.cli import main

    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    lengths = [len(B.sequence(f)) for f in va]
    w = BT.validation_windows(va, "all")
    assert len(w) == sum(n - (B.ALL_OBS + B.N_PRED) + 1 for n in lengths) and w.shape[1] == B.N_OBS + B.N_PRED
    assert np.array_equal(w[0, : B.N_OBS - B.ALL_OBS + 1], np.repeat(w[:1, 0], B.N_OBS - B.ALL_OBS + 1, 0))
    cfg = B.MlpConfig(n_obs=10, n_pred=10, n_blocks=2)
    m10 = B.DctMlp(25, cfg)
    obs = w[:3, : B.N_OBS].copy()
    obs[:, :40] += 5.0  # what lies before the newest 10 frames does not matter to it
    assert np.allclose(B.mlp_forecast(m10, obs), B.mlp_forecast(m10, w[:3, : B.N_OBS]))
    ck = tmp_path / "m10.pt"
    B.save_mlp(ck, m10, cfg, {})
    assert main(["cmu8", "validate", str(ck), "--data", str(tiny_root), "--windows", "all"]) == 0
    assert "m10.pt: validation MPJPE" in capsys.readouterr().out
    assert main(["cmu8", "validate", str(tmp_path / "none.pt"), "--data", str(tiny_root)]) == 2
    assert "is not a `forecast cmu8 train | ensemble` checkpoint" in capsys.readouterr().err


def test_ensemble_forecasts_the_members_mean_and_round_trips(tiny_root, tmp_path, capsys):
    from roomcap.forecast.cli import main

    (m1, c1), (m2, c2) = _random_mlp(1), _random_mlp(2)
    obs = np.cumsum(np.random.default_rng(0).normal(0, 0.05, (4, 50, 38, 3)), 1)
    y1, y2 = B.mlp_forecast(m1, obs), B.mlp_forecast(m2, obs)
    assert np.abs(y1 - y2).max() > 1e-3  # different members
    ck = tmp_path / "ens.pt"
    B.save_ensemble(ck, [(m1, c1), (m2, c2)], {"members": ["a", "b"]})
    assert B.is_cmu8_checkpoint(ck)
    ens, blob = B.load_mlp(ck)
    assert isinstance(ens, B.DctMlpEnsemble) and len(ens.members) == 2
    assert blob["extra"]["members"] == ["a", "b"]
    assert np.allclose(B.mlp_forecast(ens, obs), (y1 + y2) / 2, atol=1e-5)
    # the command: members scored on validation, the ensemble written and scored by evaluate
    paths = []
    for i, (m, c) in enumerate(((m1, c1), (m2, c2))):
        paths.append(tmp_path / f"m{i}.pt")
        B.save_mlp(paths[-1], m, c, {"train_files": []})
    out = tmp_path / "e2.pt"
    assert main(["cmu8", "ensemble", *map(str, paths), "--data", str(tiny_root), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "m0.pt: validation MPJPE" in text and "ensemble of 2: validation MPJPE" in text
    e2, blob2 = B.load_mlp(out)
    assert set(blob2["extra"]["member_val_mm"]) == {"m0.pt", "m1.pt"} and blob2["extra"]["val_files"]
    assert np.allclose(B.mlp_forecast(e2, obs), (y1 + y2) / 2, atol=1e-5)
    res = B.evaluate(tiny_root, mlp_checkpoints=[out], n_windows=1)
    assert len(res["models"]["e2"]["mpjpe_mm"]) == 6
    # an ensemble is not a member
    bad = ["cmu8", "ensemble", str(out), "--data", str(tiny_root), "--out", str(tmp_path / "x.pt")]
    assert main(bad) == 2
    assert "already an ensemble" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the angle metric (Table 6.7)


def test_euler_follows_the_reference_convention():
    """rotmat2euler of Martinez et al. (LTD, convSeq2Seq) is scipy's 'xyz' of the transpose; at R02 = -+1
    exactly it takes the reference's special case (E3 = 0, E2 = +-pi/2, E1 = atan2(R01, R02))."""
    from scipy.spatial.transform import Rotation

    from roomcap.forecast.lab import benchmark_cmu8_angle as A

    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec(rng.normal(size=(50, 3)) * 0.8).as_matrix()
    assert np.allclose(A.rotmat_euler(R), Rotation.from_matrix(np.swapaxes(R, -1, -2)).as_euler("xyz"))
    for sign in (1.0, -1.0):
        s, c = np.sin(0.3), np.cos(0.3)
        G = np.array([[0.0, 0.0, -sign], [s, c, 0.0], [sign * c, -sign * s, 0.0]])  # a rotation, R02 = -sign
        assert np.isclose(np.linalg.det(G), 1.0)
        assert np.allclose(A.rotmat_euler(G), [np.arctan2(0.0, -sign), sign * np.pi / 2, 0.0])
    # the root's position and rotation never count; identical maps score 0
    x = rng.normal(size=(2, 25, 117))
    y = x.copy()
    y[..., :6] += 1.0
    assert np.allclose(A.angle_error(x, y), 0.0)


def test_angle_protocol_on_a_tiny_benchmark(tiny_root, tmp_path, capsys):
    from roomcap.forecast.cli import main
    from roomcap.forecast.lab import benchmark_cmu8_angle as A

    cfg = B.MlpConfig(steps=3, batch=8, val_every=1, n_blocks=2)
    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    f, hist = A.train(tr, va, cfg)
    assert f.joints == [1 + j for j in (2, 3, 4, 9, 10, 14, 15, 21, 22, 30, 31)]  # 3-vectors after the root's
    assert set(f.dims) == {3 + 3 * j for j in (2, 3, 4, 9, 10, 14, 15, 21, 22, 30, 31)}  # the moving values
    ck = tmp_path / "angles.pt"
    A.save(ck, f, [cfg], hist)
    assert A.is_angle_checkpoint(ck) and not A.is_angle_checkpoint(tmp_path / "none.pt")
    out = tmp_path / "o"
    args = ["eval", "--protocol", "cmu8", "--metric", "angle", str(tiny_root), "--checkpoints", str(ck)]
    assert main([*args, "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["actions"] == ["soccer", "walking"] and res["actions_averaged"] == ["soccer", "walking"]
    for name in ("zero_velocity", "angles"):
        r = res["models"][name]
        assert len(r["angle_error"]) == 5 and all(v > 0 for v in r["angle_error"])
        pa = [r["per_action"][a]["angle_error"] for a in ("soccer", "walking")]
        assert np.allclose(r["angle_error"], np.mean(pa, 0))
    # zero velocity by hand: the last observed frame against the truth at the horizon frames
    ws = A.test_windows(C.benchmark_files(tiny_root))["walking"]
    hand = [
        np.mean([A.angle_error(w[None, 49:50], w[None, 50 + k : 51 + k])[0, 0] for w in ws])
        for k in A.HORIZON_FRAMES
    ]
    assert np.allclose(res["models"]["zero_velocity"]["per_action"]["walking"]["angle_error"], hand)
    ltd = res["published"]["Trajectory = LTD (Mao et al. 2019)"]
    assert ltd["average_same_actions"] == [0.255, 0.37, 0.55, 0.62, 1.005]  # soccer and walking's mean
    # a 3D evaluation refuses an angle checkpoint, and --metric angle is cmu8's
    assert (
        main(["eval", "--protocol", "cmu8", str(tiny_root), "--checkpoints", str(ck), "--out", str(out)]) == 2
    )
    assert "score them with `--metric angle`" in capsys.readouterr().err
    assert main(["eval", "--metric", "angle", "--out", str(out)]) == 2
    assert "--metric angle is a metric of --protocol cmu8 only" in capsys.readouterr().err


def test_mirrored_maps_are_the_mirror_of_the_points_and_train(tiny_root, tmp_path, monkeypatch, capsys):
    """`--angles --mirror`: each joint takes its partner's map as (x, -y, -z); the reference's forward
    kinematics of mirrored maps is the mirrored points (exactly on a left/right symmetrised skeleton, within
    the skeleton's own asymmetry on the real one); twice is the identity; training takes it."""
    from roomcap.forecast.cli import main
    from roomcap.forecast.lab import benchmark_cmu8_angle as A

    joints = list(range(1, 39))  # every joint's 3-vector
    idx = torch.from_numpy(A.mirror_index(joints))
    rng = np.random.default_rng(0)
    maps = rng.normal(0, 0.4, (1, 6, 38, 3))
    m = A.mirror_maps(torch.from_numpy(maps), torch.tensor([True]), idx).numpy()
    assert np.allclose(A.mirror_maps(torch.from_numpy(m), torch.tensor([True]), idx).numpy(), maps)

    def points(maps_: np.ndarray) -> np.ndarray:
        e = np.zeros((6, 117))
        e[:, 3:] = maps_[0].reshape(6, -1)
        return C.expmap_to_xyz(e)

    def mirrored(p: np.ndarray) -> np.ndarray:
        return p[:, list(B.MIRROR_PARTNER)] * np.array([-1.0, 1.0, 1.0])

    asym = np.abs(points(m) - mirrored(points(maps))).max()
    assert 0 < asym < 0.1 * np.abs(points(maps)).max()  # the ASF offsets differ a little left and right
    sym = 0.5 * (C.CMU38_OFFSETS + mirrored(C.CMU38_OFFSETS[None])[0])
    monkeypatch.setattr(C, "CMU38_OFFSETS", sym)
    assert np.abs(points(m) - mirrored(points(maps))).max() < 1e-9
    flip = A.mirror_maps(torch.from_numpy(maps), torch.tensor([False]), idx).numpy()
    assert np.array_equal(flip, maps)  # windows not chosen stay
    monkeypatch.undo()
    # the tiny benchmark moves the left hip but not the right one: a clear refusal
    out = tmp_path / "m.pt"
    args = ["cmu8", "train", str(tiny_root), "--angles", "--mirror", "--steps", "2", "--batch", "4"]
    assert main([*args, "--val-every", "1", "--blocks", "1", "--out", str(out)]) == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "--mirror needs both sides of each used joint; the train files move lhip" in err
    both = [2, 8, 3, 9, 14]  # left and right hip and knee, the lower back
    dims = np.array([3 * (j + 1) + k for j in both for k in range(3)])
    monkeypatch.setattr(A, "used_dims", lambda files: dims)
    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    f, hist = A.train(tr, va, B.MlpConfig(steps=2, batch=4, val_every=1, n_blocks=1, mirror=True))
    assert f.joints == sorted(j + 1 for j in both) and np.isfinite(hist["best"]["val_rad"])


def test_angle_ensemble_forecasts_the_members_mean_and_reads_the_one_model_format(
    tiny_root, tmp_path, capsys
):
    """`forecast cmu8 ensemble` of angle models: the members' mean forecast, scored on validation; a
    checkpoint written before ensembles (one model's config and ``weights["model"]``) still loads."""
    from roomcap.forecast.cli import main
    from roomcap.forecast.lab import benchmark_cmu8_angle as A
    from roomcap.forecast.runtime.checkpoint import write_checkpoint

    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    paths, fs = [], []
    for seed in (0, 1):
        cfg = B.MlpConfig(steps=3, batch=8, val_every=1, n_blocks=2, n_pred=10, seed=seed)
        f, hist = A.train(tr, va, cfg)
        paths.append(tmp_path / f"a{seed}.pt")
        A.save(paths[-1], f, [cfg], hist)
        fs.append(f)
    obs = A.test_windows(C.benchmark_files(tiny_root))["walking"][:, : B.N_OBS]
    y0, y1 = fs[0](obs), fs[1](obs)
    assert np.abs(y0 - y1).max() > 1e-4  # different members
    out = tmp_path / "ens.pt"
    assert main(["cmu8", "ensemble", *map(str, paths), "--data", str(tiny_root), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "a0.pt: validation angle error" in text and "ensemble of 2: validation angle error" in text
    ens, blob = A.load(out)
    assert isinstance(ens.model, B.DctMlpEnsemble) and blob["extra"]["members"] == ["a0.pt", "a1.pt"]
    # the mean of the members' passes, rolled out pass by pass: close to, not equal to, the mean of rollouts
    first = np.mean([f(obs)[:, :10] for f in fs], 0)
    assert np.allclose(ens(obs)[:, :10], first, atol=1e-5)
    bad = [
        "cmu8",
        "ensemble",
        str(out),
        str(paths[0]),
        "--data",
        str(tiny_root),
        "--out",
        str(tmp_path / "x.pt"),
    ]
    assert main(bad) == 2 and "already an ensemble" in capsys.readouterr().err
    old = tmp_path / "old.pt"  # the format before ensembles
    f0 = fs[0]
    write_checkpoint(
        old, A.FAMILY, config=B.MlpConfig(n_blocks=2, n_pred=10), weights={"model": f0.model.state_dict()},
        extra={}, vectors=f0.joints, dims=[int(d) for d in f0.dims], fps=B.FPS,
    )  # fmt: skip
    assert np.allclose(A.load(old)[0](obs), y0, atol=1e-6)


def test_shipped_angle_checkpoint_forecasts_below_zero_velocity():
    """The shipped exponential-map forecaster (picked on validation) loads and, on the walking test file's
    protocol windows, beats zero velocity at every horizon."""
    from roomcap.forecast.lab import benchmark_cmu8_angle as A

    need_shared("data", "motion", "cmu-more", "benchmark-cmu8", "test", "walking", "walking_1.txt")
    f, blob = A.load(A.SHIPPED)
    assert blob["model"] == A.FAMILY and 0 < blob["extra"]["best"]["val_rad"] < 1.0
    w = A.test_windows(C.benchmark_files())["walking"]
    ours = A.at_horizons(A.score(f(w[:, : B.N_OBS]), w[:, B.N_OBS :], f.dims))
    zero = A.at_horizons(A.score(A.zero_velocity(w[:, : B.N_OBS]), w[:, B.N_OBS :], None))
    assert all(o < z for o, z in zip(ours, zero, strict=True)), (ours, zero)


# ----------------------------------------------------------------------------- the intention model on angles


def test_intention_model_on_the_angle_protocol(tiny_root, tmp_path, capsys):
    """`forecast cmu8 train --angles --model intention`: the seed's intention model on the used
    exponential-map values, its checkpoint in the one format with a card, samples of the protocol's shape,
    best-of-k scored as the sample closest to the truth, and `forecast eval --metric angle` beside zero
    velocity."""
    from roomcap.forecast.cli import main
    from roomcap.forecast.lab import benchmark_cmu8_angle as A
    from roomcap.forecast.lab import benchmark_cmu8_angle_intention as AI
    from roomcap.forecast.lab.metrics import closest_sequence_error

    ck = tmp_path / "intent.pt"
    args = ["cmu8", "train", str(tiny_root), "--angles", "--model", "intention", "--out", str(ck)]
    assert main([*args, "--steps", "3", "--batch", "4", "--hidden", "16", "--val-every", "2"]) == 0
    assert "validation angle error" in capsys.readouterr().out
    f, blob = AI.load(ck)
    assert blob["model"] == A.INTENTION_FAMILY and A.is_angle_checkpoint(ck)
    assert blob["config"]["hidden"] == 16 and blob["config"]["n_obs"] == 50 and blob["config"]["n_pred"] == 25
    assert [v["step"] for v in blob["extra"]["val"]] == [2, 3] and blob["extra"]["best"]["step"] in (2, 3)
    assert "best of" in blob["card"]["selection"] and blob["card"]["scores"]["angle_error_rad"] > 0
    assert not any(k.startswith(("D_pose.", "D_label.")) for k in blob["weights"]["model"])
    assert set(f.dims) == {3 + 3 * j for j in (2, 3, 4, 9, 10, 14, 15, 21, 22, 30, 31)}  # the used values
    assert len(np.unique(f.model.merge.numpy())) > 1  # labels merged, not all one
    # samples: the protocol's shape, seeded, the unused values the last observed frame's
    w = A.test_windows(C.benchmark_files(tiny_root))["walking"]
    obs, gt = w[:, : B.N_OBS], w[:, B.N_OBS :]
    s = f.samples(obs, 4)
    assert s.shape == (len(w), 4, 25, 117) and f(obs).shape == (len(w), 25, 117)
    assert np.array_equal(s, f.samples(obs, 4)) and np.abs(s[:, 0] - s[:, 1]).max() > 0
    unused = np.setdiff1d(np.arange(117), f.dims)
    assert np.array_equal(s[..., unused], np.broadcast_to(obs[:, None, -1:, unused], s[..., unused].shape))
    # best of k: per window the sample closest to the truth up to each frame (as ADE chooses), by hand
    best, mean = f.errors(obs, gt, 4)
    per = np.stack([A.score(s[:, i], gt, f.dims) for i in range(4)], 1)
    assert np.allclose(best, closest_sequence_error(per)) and np.allclose(mean, per.mean(1))
    assert np.all(best[:, 0] <= per[:, :, 0].max(1))
    # the evaluation: both figures, per action, beside zero velocity
    out = tmp_path / "o"
    ev = ["eval", "--protocol", "cmu8", "--metric", "angle", str(tiny_root), "--checkpoints", str(ck)]
    assert main([*ev, "--out", str(out)]) == 0
    r = json.loads((out / "results.json").read_text())["models"]["intent"]
    assert len(r["angle_error"]) == 5 and len(r[A.MEAN_OF_SAMPLES]) == 5 and "best of k" in r["scoring"]
    for a in ("soccer", "walking"):
        assert len(r["per_action"][a]["angle_error"]) == 5 and len(r["per_action"][a][A.MEAN_OF_SAMPLES]) == 5
    pa = [r["per_action"][a]["angle_error"] for a in ("soccer", "walking")]
    assert np.allclose(r["angle_error"], np.mean(pa, 0))
    assert "intent (mean of single samples)" in (out / "report.md").read_text()
    # the 3D evaluation refuses it
    assert (
        main(["eval", "--protocol", "cmu8", str(tiny_root), "--checkpoints", str(ck), "--out", str(out)]) == 2
    )
    assert "score them with `--metric angle`" in capsys.readouterr().err


def test_intention_angle_bad_input(tiny_root, tmp_path, capsys):
    """Bad input is a one-line message: --model intention without --angles, with --mirror, a short
    observation, a DCT + MLP checkpoint read as an intention one, weights that do not fit the config."""
    from roomcap.forecast.cli import main
    from roomcap.forecast.lab import benchmark_cmu8_angle as A
    from roomcap.forecast.lab import benchmark_cmu8_angle_intention as AI

    base = ["cmu8", "train", str(tiny_root), "--model", "intention", "--out", str(tmp_path / "x.pt")]
    assert main(base) == 2 and "add --angles" in capsys.readouterr().err
    assert main([*base, "--angles", "--mirror"]) == 2
    assert "not of --model intention" in capsys.readouterr().err
    assert main([*base, "--angles", "--n-obs", "10"]) == 2 and "n_obs must be 50" in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()
    cfg = AI.config(steps=1, batch=2, hidden=8, n_clusters=4, n_intentions=2, val_every=0)
    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    f, _ = AI.train(tr, va, cfg)
    with pytest.raises(InputError, match=r"needs \(W, >= 50, 117\) frames"):
        f.samples(np.zeros((2, 10, 117)), 2)
    mlp = tmp_path / "mlp.pt"
    fm, hist = A.train(tr, va, B.MlpConfig(steps=1, batch=4, val_every=1, n_blocks=1))
    A.save(mlp, fm, [B.MlpConfig(steps=1, batch=4, val_every=1, n_blocks=1)], hist)
    with pytest.raises(RoomcapError, match="'cmu8_angle_dct_mlp' checkpoint, not 'cmu8_angle_intention'"):
        AI.load(mlp)
    ck = tmp_path / "int.pt"  # a config edited after training: the weights no longer fit
    AI.save(ck, f, dataclasses.replace(cfg, hidden=16), {})
    with pytest.raises(InputError, match="the weights do not fit its config.*retrain"):
        AI.load(ck)


def test_intention_first_stage_trains_the_intention_forecaster_alone():
    """`--label-steps`: the intention forecaster alone learns L_sym (here labels that hold within a window);
    the pose forecaster's weights stay as they were."""
    from roomcap.forecast.lab import benchmark_cmu8_angle_intention as AI
    from roomcap.forecast.runtime.registry import intention_model

    cfg = AI.config(n_pred=25, batch=16, hidden=8, n_clusters=4, n_intentions=3, label_steps=200, seed=0)
    torch.manual_seed(0)
    model = intention_model(cfg, 6)
    L = cfg.n_obs + cfg.n_pred + cfg.gamma - 1
    X = torch.randn(40, L, 6)
    labels = torch.arange(40)[:, None].expand(40, L) % 3  # each window holds one intention

    def ce() -> float:
        c = labels[:, cfg.n_obs - 1 :]
        with torch.no_grad():
            logits = model.label_logits_teacher(X[:, : cfg.n_obs], c[:, :-1])
        return float(torch.nn.functional.cross_entropy(logits.reshape(-1, 3), c[:, 1:].reshape(-1)))

    before, pose = (
        ce(),
        {k: v.clone() for k, v in model.state_dict().items() if not k.startswith(("e_l", "d_l", "l_out"))},
    )
    AI.train_labels(model, X, labels, cfg, np.random.default_rng(0), reverse=True)
    assert ce() < 0.5 * before  # measured 1.09 -> 0.08
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in pose.items())


def test_intention_angle_reverse_plays_windows_backwards_with_their_labels(tiny_root, monkeypatch):
    """`--reverse` for the intention model: some windows of a batch are the same windows played backwards,
    their intention labels reversed with them; the others are unchanged."""
    from roomcap.forecast.lab import benchmark_cmu8_angle_intention as AI

    seen: list[tuple] = []
    losses = AI.intention_losses

    def spy(model, cfg, obs, fut, ones, lab):
        seen.append((obs.clone(), fut.clone(), lab.clone()))
        return losses(model, cfg, obs, fut, ones, lab)

    monkeypatch.setattr(AI, "intention_losses", spy)
    cfg = AI.config(steps=1, batch=8, hidden=8, n_clusters=4, n_intentions=2, val_every=0)
    tr, va = BT.split_train_val(C.benchmark_files(tiny_root))
    AI.train(tr, va, cfg)
    AI.train(tr, va, cfg, reverse=True)
    (obs, _, lab), (obs_r, fut_r, lab_r) = seen  # the same windows: the first batch draws the same indices
    back = [i for i in range(8) if not torch.equal(obs_r[i], obs[i])]
    assert 0 < len(back) < 8
    for i in back:  # window w played backwards: its frames 33 .. 9 are the forecast, its labels reversed
        assert torch.equal(fut_r[i], obs[i, 9:34].flip(0)) and torch.equal(lab_r[i], lab[i].flip(0))
    for i in set(range(8)) - set(back):
        assert torch.equal(lab_r[i], lab[i])
