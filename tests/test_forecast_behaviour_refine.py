"""The behaviour forecaster's pose refinement after decoding (ch. 3's eq. 3.2, a variant beyond ch. 4) and the
RepNet-layout critic."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roomcap.forecast.lab.behaviour import refine as R
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.data import JOINTS, UPPER9
from roomcap.forecast.lab.behaviour.model import (
    BehaviourConfig,
    Critic,
    RepNetCritic,
    bones,
    build,
    load_checkpoint,
    save_checkpoint,
)
from tests.test_forecast_behaviour_eval import _longer_left_forearm, _symmetric_pose

torch.set_num_threads(1)


def _blen(P: np.ndarray, names) -> np.ndarray:
    b = bones(tuple(names))
    return np.linalg.norm(P[..., b[:, 0], :] - P[..., b[:, 1], :], axis=-1)


def _pose() -> np.ndarray:
    """The symmetric body pose with a head (nose, eyes, ears)."""
    P = _symmetric_pose()
    P[JOINTS.index("nose")] = (0, 0.08, 1.62)
    for s, x in (("left", -1), ("right", 1)):
        P[JOINTS.index(f"{s}_eye")] = (0.03 * x, 0.07, 1.66)
        P[JOINTS.index(f"{s}_ear")] = (0.07 * x, 0.0, 1.65)
    return P


def _forecast(S: int = 6, m: int = 3, seed: int = 0) -> np.ndarray:
    """(S,m,19,3) poses: a symmetric pose, jittered, each later step's limbs shorter (as the forecasts)."""
    rng = np.random.default_rng(seed)
    P = np.tile(_pose(), (S, m, 1, 1))
    P += rng.normal(0, 0.03, P.shape)
    pel = JOINTS.index("pelvis")
    shrink = np.linspace(1.0, 0.8, m)[None, :, None, None]
    return (P[..., pel : pel + 1, :] + (P - P[..., pel : pel + 1, :]) * shrink).astype(np.float32)


def test_symmetric_gives_left_and_right_bones_their_mean():
    P = _longer_left_forearm(_symmetric_pose(), 0.1)
    b = bones(JOINTS)
    L = _blen(P, JOINTS)
    S = R.symmetric(L, b, JOINTS)
    fl = [i for i, (c, p) in enumerate(b) if JOINTS[c] in ("left_wrist", "right_wrist")]
    assert L[fl[0]] != pytest.approx(L[fl[1]]) and S[fl[0]] == pytest.approx(S[fl[1]])
    assert S[fl[0]] == pytest.approx(L[fl].mean())
    other = [i for i in range(len(b)) if i not in fl]
    assert np.allclose(S[other], L[other])  # symmetric pairs and unpaired bones (neck, nose) unchanged


def test_angle_pairs_are_bone_and_parent_bone():
    b = bones(JOINTS)
    pairs = R.angle_pairs(b)
    chain = [(i, j) for i, j in pairs if b[i, 1] == b[j, 0]]  # bone i starts where bone j ends
    sib = [(i, j) for i, j in pairs if b[i, 1] == b[j, 1]]  # two bones leave one joint
    assert len(chain) + len(sib) == len(pairs)
    # every bone but those leaving the root (pelvis) has a parent bone
    assert len(chain) == len(b) - sum(JOINTS[p] == "pelvis" for _, p in b)
    names = {(JOINTS[b[i, 0]], JOINTS[b[j, 0]]) for i, j in sib}
    assert ("left_hip", "right_hip") in names and ("left_shoulder", "right_shoulder") in names


@pytest.mark.parametrize("source", ["first", "database", "database_mean"])
def test_refine_takes_the_reference_bones_and_stays_near(source):
    """Eq. 3.2 without angles: every step's bones reach ``b`` (the first step's, left and right alike; or the
    database's proportions at the first step's size) while the joints move little."""
    P = _forecast()
    db = np.tile(_pose() * 1.1, (4, 1, 1)).astype(np.float32)
    cfg = R.RefineConfig(w_a=0.0, bones=source, iters=300)
    ref = R.reference_bones(P, JOINTS, cfg, db)
    X = R.refine(P, JOINTS, cfg, db)
    assert X.shape == P.shape
    before = np.abs(_blen(P, JOINTS) - ref[:, None]).mean()
    after = np.abs(_blen(X, JOINTS) - ref[:, None]).mean()
    assert before > 0.03 and after < 0.003  # metres
    assert T.symmetry(X.reshape(-1, 19, 3), JOINTS)["symmetry_mm"] < 3
    if source == "database":  # the database's proportions, the first step's size
        dbl = _blen(db[:1], JOINTS)[0]
        assert np.allclose(ref / ref[:, :1], dbl / dbl[0], atol=1e-5)
        assert np.allclose(ref.sum(1), _blen(P[:, 0], JOINTS).sum(1), rtol=1e-5)
    if source == "database_mean":  # the database's mean skeleton for everyone
        assert np.allclose(ref, _blen(db[:1], JOINTS), atol=1e-5)
    # a forecast whose bones already are the reference stays put
    Y = R.refine(X, JOINTS, cfg, db)
    assert np.abs(Y - X).max() < 0.01


def test_refine_angles_pull_towards_the_first_step():
    P = _forecast(S=4, m=2, seed=3)
    P[:, 1] = P[:, 1] + np.random.default_rng(1).normal(0, 0.1, P[:, 1].shape)  # step 2: other angles
    b, pairs = torch.as_tensor(bones(JOINTS)), torch.as_tensor(R.angle_pairs(bones(JOINTS)))

    def gap(X):
        A = R._angles(torch.as_tensor(X), b, pairs)
        return float((A[:, 1] - A[:, 0]).abs().mean())

    no = R.refine(P, JOINTS, R.RefineConfig(w_a=0.0, bones="first", angles="first"))
    yes = R.refine(P, JOINTS, R.RefineConfig(w_a=0.4, bones="first", angles="first"))
    assert gap(yes) < 0.5 * gap(no)


def test_refine_config_checks():
    with pytest.raises(ValueError, match="bones"):
        R.RefineConfig(bones="mine")
    with pytest.raises(ValueError, match="weights"):
        R.RefineConfig(w_b=-1)
    got = R.refine_config_from_dict({"w_a": "0", "bones": "first"})
    assert got == R.RefineConfig(w_a=0.0, bones="first")
    with pytest.raises(ValueError, match="angles"):
        R.RefineConfig(angles="some")
    with pytest.raises(ValueError, match="database"):
        R.reference_bones(_forecast(), JOINTS, R.RefineConfig(bones="database"), None)


def test_refined_scores_keep_the_raw_figures():
    """``evaluate_all``'s refined figures: raw 2D and the refinement's cost in px, under their own keys."""
    from tests.test_forecast_behaviour_skeleton import _tiny_prepared

    d = _tiny_prepared()
    S, m = d.tgt_3d.shape[:2]
    P = d.tgt_3d + np.random.default_rng(0).normal(0, 0.02, d.tgt_3d.shape).astype(np.float32)
    r = T._refined_scores(
        P, d, 3, d.names, None, R.RefineConfig(bones="first", angles="first", iters=50), None
    )
    raw = T.metrics(None, P, d, 3)["mpjpe2d_px"]
    assert r["refine_cost_px"] == pytest.approx(r["mpjpe2d_px_refined"] - raw)
    assert r["quality3d_refined"] is None and r["symmetry_mm_refined"] >= 0


def test_repnet_critic_and_old_checkpoints(tmp_path):
    """critic=repnet builds RepNet's layout (residual paths, wider KCS path); checkpoints without the key
    load as the plain critic's."""
    for names in (JOINTS, UPPER9):
        cfg = BehaviourConfig(critic="repnet", hidden=16, joints="body19" if names == JOINTS else "upper9")
        gen, crit = build(cfg)
        assert isinstance(crit, RepNetCritic)
        P = torch.randn(5, len(names), 3, requires_grad=True)
        s = crit(P)
        assert s.shape == (5,)
        assert torch.autograd.grad(s.sum(), P)[0].abs().sum() > 0
        assert crit.k2.in_features == 4 * crit.j2.in_features  # the KCS path 4x wider
    assert isinstance(build(BehaviourConfig(hidden=16))[1], Critic)
    with pytest.raises(ValueError, match="critic"):
        BehaviourConfig(critic="big")
    cfg = BehaviourConfig(hidden=16, critic="repnet")
    path = tmp_path / "c.pt"
    save_checkpoint(path, {"full": build(cfg)[0]}, {"full": cfg}, {})
    assert load_checkpoint(path)[1]["full"].critic == "repnet"


def test_rigid_angles_are_those_the_database_never_varies():
    """angles="rigid": the hips stay in line through the pelvis (as in every database pose) while the
    articulated angles (knees, elbows) are free of the angle term."""
    rng = np.random.default_rng(5)
    db = np.stack([_pose() for _ in range(30)])
    # the database's poses bend their elbows and knees, never their hips' line
    for k in range(30):
        for s in ("left", "right"):
            db[k, JOINTS.index(f"{s}_wrist")] += rng.normal(0, 0.1, 3)
            db[k, JOINTS.index(f"{s}_ankle")] += rng.normal(0, 0.1, 3)
    pairs, theta = R.reference_angles(_forecast(), JOINTS, R.RefineConfig(angles="rigid"), db)
    b = bones(JOINTS)
    held = {(JOINTS[b[i, 0]], JOINTS[b[j, 0]]) for i, j in pairs}
    assert ("left_hip", "right_hip") in held and ("left_shoulder", "right_shoulder") in held
    assert not any("wrist" in a + c or "ankle" in a + c for a, c in held)
    hips = [
        k for k, (i, j) in enumerate(pairs) if {JOINTS[b[i, 0]], JOINTS[b[j, 0]]} == {"left_hip", "right_hip"}
    ]
    assert theta.shape == (1, len(pairs)) and np.degrees(theta[0, hips[0]]) == pytest.approx(180, abs=0.5)
    # a forecast whose hips fold towards each other gets them back in line
    P = _forecast(S=3, m=2)
    pel = JOINTS.index("pelvis")
    for s in ("left_hip", "right_hip"):
        P[..., JOINTS.index(s), 1] += 0.08  # both hips 8 cm forward: a V at the pelvis
    cfg = R.RefineConfig(angles="rigid", bones="database", iters=400)
    X = R.refine(P, JOINTS, cfg, db)

    def hip_angle(Y):
        u = Y[..., JOINTS.index("left_hip"), :] - Y[..., pel, :]
        v = Y[..., JOINTS.index("right_hip"), :] - Y[..., pel, :]
        c = (u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
        return np.degrees(np.arccos(np.clip(c, -1, 1))).mean()

    assert hip_angle(P) < 130 and hip_angle(X) > 170
    with pytest.raises(ValueError, match="rigid"):
        R.reference_angles(P, JOINTS, R.RefineConfig(angles="rigid"), None)
