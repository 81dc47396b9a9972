"""The behaviour forecaster's skeleton layer (the 3D database's bone proportions) and its checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roomcap.forecast.lab.behaviour.data import JOINTS, UPPER9
from roomcap.forecast.lab.behaviour.model import (
    BehaviourConfig,
    Skeleton,
    bones,
    build,
    load_checkpoint,
    save_checkpoint,
)

torch.set_num_threads(1)


def _lengths(P: torch.Tensor, b: np.ndarray) -> torch.Tensor:
    return (P[:, b[:, 0]] - P[:, b[:, 1]]).norm(dim=-1)


@pytest.mark.parametrize("names", [JOINTS, UPPER9])
def test_skeleton_takes_database_proportions(names):
    rng = np.random.default_rng(0)
    b = bones(names)
    sk = Skeleton(b)
    db = rng.normal(size=(50, len(names), 3)).astype(np.float32)
    sk.set_lengths(db)
    L = np.linalg.norm(db[:, b[:, 0]] - db[:, b[:, 1]], axis=-1).mean(0)
    raw = torch.as_tensor(rng.normal(size=(7, len(names), 3)), dtype=torch.float32)
    P = sk(raw, torch.as_tensor(rng.normal(size=7) * 3, dtype=torch.float32))
    got = _lengths(P, b).numpy()
    ratio = got / L[None]
    # every bone of one pose is scaled alike (the database's proportions), within the scale's bounds
    assert np.allclose(ratio, ratio[:, :1], atol=1e-4)
    assert (np.abs(ratio[:, 0] - 1) <= sk.max_scale + 1e-6).all()
    # the pelvis stays, and each bone keeps its direction
    pel = names.index("pelvis")
    assert torch.allclose(P[:, pel], raw[:, pel])
    u_raw = raw[:, b[:, 0]] - raw[:, b[:, 1]]
    u_out = P[:, b[:, 0]] - P[:, b[:, 1]]
    cos = torch.nn.functional.cosine_similarity(u_raw, u_out, dim=-1)
    assert (cos > 1 - 1e-5).all()


def test_skeleton_size_from_its_input():
    sk = Skeleton(bones(JOINTS))
    b = sk.bone_idx.numpy()  # the layer's order (parents first)
    base = torch.as_tensor(np.random.default_rng(1).normal(size=(1, 19, 3)), dtype=torch.float32)
    sk.bone_len.copy_(_lengths(base, b)[0])
    # a = 0: the database's size, whatever the raw pose's size; a -> +-inf: the bounds
    pel = JOINTS.index("pelvis")
    big, same = sk(base * 3, torch.zeros(1)), sk(base, torch.zeros(1))
    assert torch.allclose(big - big[:, pel : pel + 1], same - same[:, pel : pel + 1], atol=1e-5)
    assert torch.allclose(sk(base, torch.zeros(1)), base, atol=1e-5)
    for a, want in ((50.0, 1 + sk.max_scale), (-50.0, 1 - sk.max_scale)):
        r = _lengths(sk(base, torch.tensor([a])), b) / sk.bone_len
        assert torch.allclose(r, torch.full_like(r, want), atol=1e-5)


def _written_before(path, option: str):
    """A checkpoint of the default model written before ``option`` existed (its config lacks the key),
    loaded back -> (generators, configs)."""
    cfg = BehaviourConfig(hidden=32)
    save_checkpoint(path, {"full": build(cfg)[0]}, {"full": cfg}, {})
    blob = torch.load(path, weights_only=True)
    del blob["config"]["full"][option]
    torch.save(blob, path)
    gens, cfgs, _ = load_checkpoint(path)
    return gens, cfgs


def test_skeleton_checkpoint_and_older_configs(tmp_path):
    cfg = BehaviourConfig(hidden=32, bone_lengths="database")
    gen, _ = build(cfg)
    assert gen.skeleton is not None
    P = gen(torch.randn(2, cfg.n_obs, 19, 3), torch.zeros(2, cfg.n_obs, 8), torch.zeros(2, 9))[1]
    assert P.shape == (2, 19, 3)
    gen.skeleton.bone_len.fill_(0.3)
    path = tmp_path / "b.pt"
    save_checkpoint(path, {"full": gen}, {"full": cfg}, {})
    gens, cfgs, _ = load_checkpoint(path)
    assert cfgs["full"].bone_lengths == "database"
    assert torch.equal(gens["full"].skeleton.bone_len, gen.skeleton.bone_len)
    # a checkpoint written before the option existed holds free joints
    gens, cfgs = _written_before(path, "bone_lengths")
    assert cfgs["full"].bone_lengths == "free" and gens["full"].skeleton is None
    with pytest.raises(ValueError, match="bone_lengths"):
        BehaviourConfig(bone_lengths="rigid")
    with pytest.raises(ValueError, match="n_critic"):
        BehaviourConfig(n_critic=0)


def _tiny_prepared(S: int = 16):
    from roomcap.forecast.lab.behaviour import geometry
    from roomcap.forecast.lab.behaviour.data import ACTIONS
    from roomcap.forecast.lab.behaviour.training import Prepared
    from roomcap.synthetic.rigs import ring_rig

    rng = np.random.default_rng(2)
    rig = ring_rig(6, 4.0, height_m=2.2)
    cams = [rig[int(i)] for i in rng.integers(6, size=S)]
    view = geometry.make_view(
        np.stack([c.K for c in cams]),
        np.stack([c.R for c in cams]),
        np.stack([c.t for c in cams]),
        np.c_[rng.uniform(-1, 1, (S, 2)), np.zeros(S)],
    )
    f32 = np.float32
    return Prepared(
        JOINTS,
        view,
        rng.normal(0, 0.3, (S, 3, 19, 2)).astype(f32),
        np.ones((S, 3, 19), bool),
        rng.uniform(500, 700, (S, 3, 19, 2)).astype(f32),
        rng.integers(len(ACTIONS), size=(S, 8)),
        rng.uniform(500, 700, (S, 5, 19, 2)).astype(f32),
        rng.normal(0, 0.3, (S, 5, 19, 3)).astype(f32),
    )


def test_training_steps_with_skeleton_and_n_critic():
    """n_critic critic updates per generator update, and a trained skeleton model's poses keep the
    database's proportions."""
    from roomcap.forecast.lab.behaviour import training as T

    tr = _tiny_prepared()
    db = np.random.default_rng(3).normal(0, 0.4, (40, 19, 3)).astype(np.float32)
    cfg = BehaviourConfig(hidden=16, batch=8, n_critic=3, bone_lengths="database", short_history=0.0)
    f = T._fit_state(cfg, db)
    for _ in range(2):
        losses = T._generator_step(f, tr)
        assert len(losses) == 3 and all(np.isfinite(losses))
    steps = {int(s["step"]) for s in f.oc.state.values()}
    assert steps == {6}  # 2 generator steps x 3 critic steps
    assert {int(s["step"]) for s in f.og.state.values()} == {2}
    _, P = T.predict(f.gen, cfg, tr)
    b = f.gen.skeleton.bone_idx.numpy()
    L = np.linalg.norm(P[..., b[:, 0], :] - P[..., b[:, 1], :], axis=-1)
    ratio = L / f.gen.skeleton.bone_len.numpy()
    assert np.allclose(ratio, ratio[..., :1], atol=1e-4)
    want = np.linalg.norm(db[:, b[:, 0]] - db[:, b[:, 1]], axis=-1).mean(0)
    assert np.allclose(f.gen.skeleton.bone_len.numpy(), want, atol=1e-5)


def test_learned_proportions_train_and_round_trip(tmp_path):
    """bone_lengths=learned: the proportions start at the database's, move with the loss, stay one set for
    every pose, and come back from a checkpoint."""
    cfg = BehaviourConfig(hidden=32, bone_lengths="learned")
    gen, _ = build(cfg)
    sk = gen.skeleton
    assert sk is not None and sk.log_ratio is not None
    assert "skeleton.log_ratio" in dict(gen.named_parameters())
    b = sk.bone_idx.numpy()
    sk.bone_len.fill_(0.2)
    assert torch.allclose(sk.lengths(), sk.bone_len)  # the database's proportions at the start
    # a loss on one bone's length moves that bone's learned ratio (and no pose-independent ratio is frozen)
    opt = torch.optim.SGD([sk.log_ratio], lr=1.0)
    raw = torch.randn(4, 19, 3)
    for _ in range(3):
        loss = _lengths(sk(raw, torch.zeros(4)), b)[:, 0].sub(0.3).pow(2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    L = sk.lengths().detach()
    assert L[0] > 0.2 + 1e-3 and torch.allclose(L[1:], sk.bone_len[1:])
    got = _lengths(sk(raw, torch.zeros(4)), b).detach()
    assert torch.allclose(got, L.expand_as(got), atol=1e-5)  # one skeleton for every pose
    path = tmp_path / "l.pt"
    save_checkpoint(path, {"full": gen}, {"full": cfg}, {})
    gens, cfgs, _ = load_checkpoint(path)
    assert cfgs["full"].bone_lengths == "learned"
    assert torch.allclose(gens["full"].skeleton.lengths(), L)
    # the fixed skeleton has no learned ratios
    assert build(BehaviourConfig(hidden=32, bone_lengths="database"))[0].skeleton.log_ratio is None


def _canonical_db(n: int = 64) -> np.ndarray:
    """Two poses (19 joints), half the set each, with 1 cm joint noise, in the canonical frame."""
    from roomcap.forecast.lab.behaviour.training import _canonical

    rng = np.random.default_rng(4)
    two = rng.normal(0, 0.4, (2, 19, 3))
    return _canonical((two[np.arange(n) % 2] + rng.normal(0, 0.01, (n, 19, 3))).astype(np.float32), JOINTS)


def test_pose_prior_decodes_heading_place_and_size():
    """pose_decoder=prior: the pose is the prior's decoded pose turned by the heading, scaled within the
    size bounds and moved to the pelvis output; the trained prior reconstructs its database."""
    from roomcap.forecast.lab.behaviour.model import PosePrior, fit_pose_prior

    canon = _canonical_db()
    prior = fit_pose_prior(canon, BehaviourConfig(prior_dim=4, prior_steps=300))
    assert not any(p.requires_grad for p in prior.parameters())
    with torch.no_grad():
        x = torch.from_numpy(canon).reshape(len(canon), -1)
        rec = prior.dec(prior.enc(x).chunk(2, 1)[0]).reshape(-1, 19, 3)
    apart = np.linalg.norm(canon[0] - canon[1], axis=-1).mean()
    assert float((rec - torch.from_numpy(canon)).norm(dim=-1).mean()) < 0.2 * apart  # it tells the two apart
    out = torch.zeros(3, prior.n_inputs)
    out[:, prior.dim] = 1.0  # heading 0
    out[1, prior.dim : prior.dim + 2] = torch.tensor([0.0, 1.0])  # 90 degrees
    out[2, prior.dim + 2 : prior.dim + 5] = torch.tensor([1.0, 2.0, 0.5])
    out[2, -1] = 100.0  # the largest size
    with torch.no_grad():
        P = prior(out)
        X = prior.dec(torch.zeros(1, prior.dim)).reshape(19, 3)
    assert torch.allclose(P[0], X, atol=1e-5)
    assert torch.allclose(P[1, :, 0], -X[:, 1], atol=1e-5) and torch.allclose(P[1, :, 1], X[:, 0], atol=1e-5)
    assert torch.allclose(P[2], X * (1 + prior.max_scale) + torch.tensor([1.0, 2.0, 0.5]), atol=1e-5)
    assert isinstance(PosePrior(19, 4), torch.nn.Module)


def test_pose_prior_trains_frozen_and_round_trips(tmp_path):
    from roomcap.forecast.lab.behaviour import training as T

    tr = _tiny_prepared()
    db = np.random.default_rng(3).normal(0, 0.4, (40, 19, 3)).astype(np.float32)
    cfg = BehaviourConfig(
        hidden=16, batch=8, pose_decoder="prior", prior_dim=4, prior_steps=50, short_history=0.0
    )
    f = T._fit_state(cfg, db)
    prior0 = {k: v.clone() for k, v in f.gen.prior.state_dict().items()}
    gen0 = {k: v.clone() for k, v in f.gen.state_dict().items() if not k.startswith("prior.")}
    for _ in range(2):
        assert all(np.isfinite(T._generator_step(f, tr)))
    # the forecaster learns, the prior stays as trained on the database
    assert all(torch.equal(v, prior0[k]) for k, v in f.gen.prior.state_dict().items())
    assert any(not torch.equal(v, gen0[k]) for k, v in f.gen.state_dict().items() if k in gen0)
    path = tmp_path / "p.pt"
    save_checkpoint(path, {"full": f.gen}, {"full": cfg}, {})
    gens, cfgs, _ = load_checkpoint(path)
    assert cfgs["full"].pose_decoder == "prior"
    _, P0 = T.predict(f.gen, cfg, tr)
    _, P1 = T.predict(gens["full"], cfgs["full"], tr)
    assert np.array_equal(P0, P1)
    # an older checkpoint's config has no pose_decoder: the free decoder
    gens, cfgs = _written_before(path, "pose_decoder")
    assert cfgs["full"].pose_decoder == "free" and gens["full"].prior is None
    with pytest.raises(ValueError, match="pose_decoder"):
        BehaviourConfig(pose_decoder="vae")
    with pytest.raises(ValueError, match="bone_lengths=free"):
        BehaviourConfig(pose_decoder="prior", bone_lengths="database")


def test_prior_proportions_vary_bones_within_bounds_left_and_right_alike():
    from roomcap.forecast.lab.behaviour.model import _with_proportions

    X = torch.from_numpy(_canonical_db(8))
    Y = _with_proportions(X, JOINTS, 0.15, torch.Generator().manual_seed(0))
    b = bones(JOINTS)
    r = (_lengths(Y, b) / _lengths(X, b)).numpy()
    assert (np.abs(r - 1) <= 0.15 + 1e-5).all() and r.std() > 0.02
    kids = [JOINTS[c] for c, _ in b]
    for i, k in enumerate(kids):
        if k.startswith("left_"):
            assert np.allclose(r[:, i], r[:, kids.index("right_" + k[5:])], atol=1e-5)
    pel = JOINTS.index("pelvis")
    assert torch.equal(Y[:, pel], X[:, pel])
    cos = torch.nn.functional.cosine_similarity(
        Y[:, b[:, 0]] - Y[:, b[:, 1]], X[:, b[:, 0]] - X[:, b[:, 1]], dim=-1
    )
    assert (cos > 1 - 1e-5).all()
