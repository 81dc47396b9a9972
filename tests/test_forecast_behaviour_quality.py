"""The 3D quality metric as the seed defines it (Diller sec. 4.5.1, 4.7.7): one classifier trained once on
database poses vs poses collected during training, a method scored by the share of its poses judged real."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from roomcap.core.errors import FormatError
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.data import JOINTS
from roomcap.forecast.lab.behaviour.model import BehaviourConfig
from tests.conftest import need_shared
from tests.test_forecast_behaviour_skeleton import _tiny_prepared

torch.set_num_threads(1)


def _poses(rng, n: int, noise_m: float, scale: tuple[float, float]) -> np.ndarray:
    """A fixed body (the first draw of seed 0) with per-joint noise, a per-pose size and a random heading."""
    body = np.random.default_rng(0).normal(0, 0.4, (19, 3))
    X = body + rng.normal(0, noise_m, (n, 19, 3))
    X *= rng.uniform(*scale, (n, 1, 1))
    a = rng.uniform(-np.pi, np.pi, n)
    c, s = np.cos(a), np.sin(a)
    x, y = X[..., 0].copy(), X[..., 1].copy()
    X[..., 0], X[..., 1] = c[:, None] * x - s[:, None] * y, s[:, None] * x + c[:, None] * y
    return X.astype(np.float32)


def test_database_poses_judged_real_distorted_poses_fake(tmp_path):
    rng = np.random.default_rng(1)
    real = _poses(rng, 600, 0.01, (0.95, 1.05))
    fake = np.concatenate([_poses(rng, 300, 0.15, (0.95, 1.05)), _poses(rng, 300, 0.01, (0.55, 0.75))])
    q = Q.fit(real, fake, JOINTS, seed=0, steps=300)
    assert q.meta["n_real"] == 600 and q.meta["n_fake"] == 600
    held_real = _poses(rng, 400, 0.01, (0.95, 1.05))
    assert T.share_real(q.clf, held_real, JOINTS) > 0.9
    assert T.share_real(q.clf, _poses(rng, 400, 0.2, (0.95, 1.05)), JOINTS) < 0.1  # joints scattered
    assert T.share_real(q.clf, _poses(rng, 400, 0.01, (0.5, 0.7)), JOINTS) < 0.1  # bones far too short
    # the same classifier back from disk scores the same
    Q.save(tmp_path / "q.pt", q)
    q2 = Q.load(tmp_path / "q.pt")
    assert q2.joints == JOINTS and q2.meta == q.meta
    assert T.share_real(q2.clf, held_real, JOINTS) == T.share_real(q.clf, held_real, JOINTS)
    assert T.share_real(q.clf, held_real[:0], JOINTS) == 0.0
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="quality classifier"):
        Q.load(tmp_path / "bad.pt")


def test_snapshots_from_step_zero_every_n_steps():
    tr = _tiny_prepared()
    db = np.random.default_rng(3).normal(0, 0.4, (40, 19, 3)).astype(np.float32)
    cfg = BehaviourConfig(hidden=16, batch=8, steps=4, short_history=0.0)
    snaps = Q.snapshot_poses(cfg, tr, db, every=2, per_snapshot=5)
    assert [s for s, _ in snaps] == [0, 2, 4]
    assert all(p.shape == (5 * cfg.m, 19, 3) and np.isfinite(p).all() for _, p in snaps)
    assert not np.allclose(snaps[0][1], snaps[-1][1])  # the network moved between snapshots


def test_pool_weighs_every_source_alike():
    """Sec. 4.7.7's pool over every compared model: each source enters with as many poses as the largest,
    its own poses all in, a smaller source's repeated."""
    rng = np.random.default_rng(0)
    big = [(0, rng.normal(size=(6, 19, 3))), (2, rng.normal(size=(6, 19, 3)))]
    small = [(2, np.full((1, 19, 3), 7.0)), (4, np.full((1, 19, 3), 8.0))]
    fake, info = Q.pool_fakes({"full": big, "train_average": small}, seed=1)
    assert fake.shape == (24, 19, 3) and fake.dtype == np.float32
    assert info == {
        "full": {"n_poses": 12, "n_pooled": 12, "snapshot_steps": [0, 2]},
        "train_average": {"n_poses": 2, "n_pooled": 12, "snapshot_steps": [2, 4]},
    }
    assert np.allclose(fake[:12], np.concatenate([p for _, p in big]))
    ta = fake[12:, 0, 0]
    assert set(ta.tolist()) == {7.0, 8.0} and ta[0] == 7.0 and ta[1] == 8.0  # both snapshots, then repeats
    with pytest.raises(ValueError, match="at least one snapshot"):
        Q.pool_fakes({"full": big, "pose_only": []})


def test_train_average_snapshots_are_its_running_mean():
    """The train-average baseline's "training": the mean target pose of the sequences drawn so far, on the
    networks' schedule; its last snapshot is near the mean over the whole training set."""
    tr = _tiny_prepared()
    cfg = BehaviourConfig(batch=8, steps=6, seed=3)
    snaps = Q.train_average_snapshots(cfg, tr, every=2)
    assert [s for s, _ in snaps] == [2, 4, 6] and all(p.shape == (1, 19, 3) for _, p in snaps)
    drawn = np.random.default_rng(3).integers(len(tr), size=6 * 8)
    for step, p in snaps:
        assert np.allclose(p[0], T.train_average(tr.take(drawn[: step * 8])), atol=1e-5)
    assert not np.allclose(snaps[0][1], snaps[-1][1])
    assert np.abs(snaps[-1][1][0] - T.train_average(tr)).max() < np.abs(tr.tgt_3d).max()


def test_quality_then_eval_commands_tiny(tmp_path, capsys):
    """`quality` builds the classifier once; `eval` scores every pose-predicting method with it."""
    need_shared("data", "motion", "cmu-more", "single", "14")
    from roomcap.forecast.lab.behaviour.cli import main

    sets = ["steps=4", "eval_every=2", "n_train=120", "n_eval=60", "hidden=16"]
    qp, ck, res = tmp_path / "q.pt", tmp_path / "t.pt", tmp_path / "r.json"
    args = ["--every", "2", "--per-snapshot", "20", "--clf-steps", "30"]
    assert main(["quality", "--out", str(qp), "--set", *sets, *args]) == 0
    meta = Q.load(qp).meta
    # the pool: every compared model that outputs 3D poses, each weighing as much
    steps = {"full": [0, 2, 4], "pose_only": [0, 2, 4], "action_2d": [0, 2, 4]}
    assert meta["snapshot_steps"] == steps
    assert {n: s["snapshot_steps"] for n, s in meta["sources"].items()} == {**steps, "train_average": [2, 4]}
    assert {s["n_pooled"] for s in meta["sources"].values()} == {3 * 20 * 5}
    assert meta["sources"]["train_average"]["n_poses"] == 2 and meta["baselines"] == ["train_average"]
    assert meta["n_fake"] == 4 * 3 * 20 * 5 and meta["n_real"] > 1000
    assert main(["train", "--out", str(ck), "--eval-split", "none", "--set", *sets]) == 0
    argv = ["eval", "--checkpoint", str(ck), "--split", "val", "--out", str(res)]
    assert main([*argv, "--quality-classifier", str(qp)]) == 0
    r = json.loads(res.read_text())
    for n in ("full", "pose_only", "train_average"):
        assert 0 <= r["models"][n]["quality3d"] <= 1 and 0 <= r["models"][n]["quality3d_per_method"] <= 0.5
    assert r["models"]["action_only"]["quality3d"] is None and 0 <= r["models"]["true_3d"]["quality3d"] <= 1
    assert r["quality3d_classifier"]["not_in_pool"] == [] and r["quality3d_classifier"]["n_fake"] == 1200
    capsys.readouterr()
    assert main([*argv, "--quality-classifier", str(tmp_path / "none.pt")]) == 2
    assert "forecast behaviour quality" in capsys.readouterr().err
