"""The behaviour forecaster's evaluation as the seed reports it (Diller Tables 4.1, 4.2, 4.10): the symmetry
check, the action_2d ablation, the top-1 ceiling and the results.json schema of `forecast behaviour eval`."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from roomcap.forecast.lab.behaviour import data as bdata
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.data import JOINTS, UPPER9
from roomcap.forecast.lab.behaviour.model import BehaviourConfig
from tests.conftest import need_shared
from tests.test_forecast_behaviour_skeleton import _tiny_prepared

torch.set_num_threads(1)


def _symmetric_pose() -> np.ndarray:
    """A body19 pose whose left and right limbs mirror each other in x (metres)."""
    P = np.zeros((19, 3))
    side = {"shoulder": (0.2, 1.45), "elbow": (0.25, 1.15), "wrist": (0.3, 0.9)}
    side |= {"hip": (0.1, 0.95), "knee": (0.12, 0.5), "ankle": (0.12, 0.08)}
    for j, (x, z) in side.items():
        P[JOINTS.index(f"left_{j}")] = (-x, 0.0, z)
        P[JOINTS.index(f"right_{j}")] = (x, 0.0, z)
    P[JOINTS.index("pelvis")] = (0, 0, 0.95)
    P[JOINTS.index("neck")] = (0, 0, 1.5)
    return P


def _longer_left_forearm(P: np.ndarray, by_m: float) -> np.ndarray:
    Q = P.copy()
    e, w = JOINTS.index("left_elbow"), JOINTS.index("left_wrist")
    u = (Q[w] - Q[e]) / np.linalg.norm(Q[w] - Q[e])
    Q[w] += by_m * u
    return Q


def test_symmetry_is_the_median_left_right_difference():
    """Table 4.10: per pose the mean |left - right| over upper arm, forearm, thigh and shin, in mm; the
    model's figure is the median over its poses."""
    P = _symmetric_pose()
    assert T.symmetry(P[None], JOINTS)["symmetry_mm"] == pytest.approx(0.0, abs=1e-9)
    assert T.symmetry(1.3 * P[None], JOINTS)["symmetry_mm"] == pytest.approx(
        0.0, abs=1e-9
    )  # size is not asymmetry
    poses = np.stack([_longer_left_forearm(P, d) for d in (0.0, 0.04, 0.4)])
    s = T.symmetry(poses, JOINTS)
    assert s["symmetry_mm"] == pytest.approx(10.0, abs=1e-6)  # per pose 0, 10, 100 mm: median 10
    assert s["symmetry_mm_by_bone"] == pytest.approx({"upper_arm": 0, "forearm": 40, "thigh": 0, "shin": 0})
    # any leading shape; the 9 upper-body joints hold only the arms
    assert T.symmetry(poses[None], JOINTS)["symmetry_mm"] == pytest.approx(10.0, abs=1e-6)
    up = poses[:, [JOINTS.index(n) for n in UPPER9]]
    su = T.symmetry(up, UPPER9)
    assert sorted(su["symmetry_mm_by_bone"]) == ["forearm", "upper_arm"]
    assert su["symmetry_mm"] == pytest.approx(20.0, abs=1e-6)  # per pose 0, 20, 200 mm
    assert T.symmetry(None, JOINTS) is None
    assert T.symmetry(np.zeros((3, 3)), ("neck", "pelvis", "nose")) is None


def test_action_2d_trains_without_the_critic():
    """Table 4.2's ablation: action and 2D losses, no 3D adversarial loss (its critic never steps)."""
    tr = _tiny_prepared()
    db = np.random.default_rng(3).normal(0, 0.4, (40, 19, 3)).astype(np.float32)
    steps = {}
    for v in ("action_2d", "full"):
        cfg = BehaviourConfig(variant=v, hidden=16, batch=8, short_history=0.0)
        assert cfg.use_action and cfg.use_pose and cfg.use_adv3d == (v == "full")
        f = T._fit_state(cfg, db)
        assert f.la > 0 and f.l2 > 0 and (f.lv > 0) == (v == "full")
        before = [p.detach().clone() for p in f.gen.dec_pose.parameters()]
        losses = [T._generator_step(f, tr) for _ in range(2)]
        steps[v] = {int(s["step"]) for s in f.oc.state.values()}
        assert all(np.isfinite(x).all() for x in losses)
        # the 2D loss trains the pose decoder in both
        assert any(not torch.equal(a, b) for a, b in zip(before, f.gen.dec_pose.parameters(), strict=True))
        if v == "action_2d":
            assert all(x[2] == 0.0 for x in losses)
    assert steps == {"action_2d": set(), "full": {2}}


def _states_prepared(acts: np.ndarray, states: np.ndarray) -> T.Prepared:
    S, L = acts.shape
    z = np.zeros((S, 1, 19, 2), np.float32)
    return T.Prepared(JOINTS, None, z, z[..., 0] > 0, z, acts, z, z, states)


def test_top1_ceiling_uses_the_hidden_state():
    """The ceiling is the chain forecast from the last observed hidden state: on "markov" (state = label) it
    equals forward filtering on the labels; on "stations", place adds what the labels alone cannot tell."""
    rng = np.random.default_rng(0)
    n_obs, m = 3, 5
    for script in ("markov", "stations"):
        ch = bdata.script_chain(script)
        S = 3000
        st = np.zeros((S, n_obs + m), np.int64)
        st[:, 0] = rng.choice(len(ch.states), S, p=ch.pi)
        for k in range(1, n_obs + m):
            st[:, k] = [rng.choice(len(ch.states), p=ch.T[s]) for s in st[:, k - 1]]
        acts = ch.action[st]
        d = _states_prepared(acts, st)
        c = T.ceiling_top1(d, script, n_obs, m)
        labels = T.metrics(bdata.chain_forecast(ch, acts[:, :n_obs], m), None, d, n_obs)["top1"]
        if script == "markov":
            assert c["ceiling_top1"] == pytest.approx(labels)
        else:
            assert c["ceiling_top1"] > labels + 0.02  # measured 49 % against 45 % (bench --ceilings)
        assert len(c["ceiling_top1_by_step"]) == m and 0 < c["ceiling_top1"] <= 1
    assert T.ceiling_top1(_states_prepared(acts, None), "stations", n_obs, m) is None
    # a subset keeps its states; sets joined keep theirs, unless one lacks them
    tp = dataclasses.replace(_tiny_prepared(), states=st[:16])
    assert np.array_equal(tp.take(np.arange(4)).states, st[:4])
    assert T.concat([tp.take([0]), tp.take([1])]).states.tolist() == st[:2].tolist()
    assert T.concat([tp, _tiny_prepared()]).states is None


SETS = ["steps=4", "eval_every=2", "n_train=120", "n_eval=60", "hidden=16"]


@pytest.mark.parametrize("script", ["markov", "stations"])
def test_eval_results_schema_tiny(tmp_path, script):
    """results.json: models.<name>.{mpjpe2d_px, top1, quality3d, symmetry_mm} for every trained variant and
    baseline, true_3d (quality, symmetry), ceiling_top1; a variant the checkpoint lacks is absent."""
    need_shared("data", "motion", "cmu-more", "single", "14")
    from roomcap.forecast.lab.behaviour import quality as Q
    from roomcap.forecast.lab.behaviour.cli import main

    ck, res, qp = tmp_path / "t.pt", tmp_path / "r.json", tmp_path / "q.pt"
    sets = [*SETS, f"script={script}"]
    args = ["--every", "2", "--per-snapshot", "10", "--clf-steps", "20", "--variants", "full"]
    assert main(["quality", "--out", str(qp), "--set", *sets, *args]) == 0
    assert Q.load(qp).meta["variants"] == ["full"]
    assert main(["train", "--out", str(ck), "--eval-split", "none", "--set", *sets]) == 0
    argv = [
        "eval",
        "--checkpoint",
        str(ck),
        "--split",
        "val",
        "--out",
        str(res),
        "--quality-classifier",
        str(qp),
    ]
    assert main(argv) == 0
    r = json.loads(res.read_text())
    models = r["models"]
    # --refine: the refined figures of every pose model beside the raw ones, which stay as they were
    assert main([*argv, "--refine", "--refine-set", "iters=5"]) == 0
    rr = json.loads(res.read_text())
    assert rr["refine"]["iters"] == 5 and rr["refine"]["models"] == ["full", "pose_only", "action_2d"]
    for n in ("full", "pose_only", "action_2d"):
        m = rr["models"][n]
        assert m["mpjpe2d_px"] == pytest.approx(models[n]["mpjpe2d_px"])
        assert m["refine_cost_px"] == pytest.approx(m["mpjpe2d_px_refined"] - m["mpjpe2d_px"])
        assert 0 <= m["quality3d_refined"] <= 1 and m["symmetry_mm_refined"] >= 0
    assert "mpjpe2d_px_refined" not in rr["models"]["train_average"]
    assert any("refinement" in t["title"] for t in rr["tables"])
    want = {"full", "action_only", "pose_only", "action_2d", "zero_velocity", "train_average", "true_3d"}
    assert set(models) == want
    for n in want - {"true_3d"}:
        assert {"mpjpe2d_px", "top1", "quality3d", "symmetry_mm"} <= set(models[n]), n
    for n in ("full", "pose_only", "action_2d", "train_average", "true_3d"):
        assert 0 <= models[n]["quality3d"] <= 1 and models[n]["symmetry_mm"] >= 0, n
    for n in ("full", "pose_only", "action_2d", "zero_velocity", "train_average"):
        assert models[n]["mpjpe2d_px"] > 0, n
    for n in ("full", "action_only", "action_2d", "zero_velocity", "train_average"):
        assert 0 <= models[n]["top1"] <= 1, n
    assert models["action_only"]["mpjpe2d_px"] is None and models["action_only"]["symmetry_mm"] is None
    assert models["pose_only"]["top1"] is None and models["zero_velocity"]["symmetry_mm"] is None
    assert set(models["true_3d"]) == {"quality3d", "symmetry_mm", "symmetry_mm_by_bone"}
    # the true 3D are real people: their limbs differ left to right by millimetres, not centimetres
    assert models["true_3d"]["symmetry_mm"] < 20
    assert 0 < r["ceiling_top1"] <= 1 and r["script"] == script
    # the classifier's pool had the full model and the train average only: the others are named
    assert r["quality3d_classifier"]["not_in_pool"] == ["action_2d", "pose_only"]
    # the ceiling bounds the baselines that forecast from the labels (a little slack: 60 sequences)
    assert r["ceiling_top1"] >= models["zero_velocity"]["top1"] - 0.05
    # a checkpoint with some variants: the others are absent, not faked
    ck2 = tmp_path / "two.pt"
    assert (
        main(
            [
                "train",
                "--out",
                str(ck2),
                "--eval-split",
                "none",
                "--variants",
                "action_2d,pose_only",
                "--set",
                *sets,
            ]
        )
        == 0
    )
    assert main([*argv[:2], str(ck2), *argv[3:]]) == 0
    assert set(json.loads(res.read_text())["models"]) == {
        "pose_only",
        "action_2d",
        "zero_velocity",
        "train_average",
        "true_3d",
    }


@pytest.mark.parametrize(
    "extra, msg",
    [(["--refine-set", "iters=5"], "give --refine too"), (["--refine", "--refine-set", "w_a=-1"], "weights")],
)
def test_eval_refine_bad_settings(tmp_path, capsys, extra, msg):
    """Bad refinement settings are one line and exit 2 (before any data is read)."""
    from roomcap.forecast.lab.behaviour.cli import main

    assert main(["eval", "--out", str(tmp_path / "r.json"), *extra]) == 2
    assert msg in capsys.readouterr().err
