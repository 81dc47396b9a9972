"""Behaviour forecaster (Diller ch. 4): how low can the 2D error of any pose forecaster go on a script's data?

The 2D target of issue 41 is ``full <= 0.9 x min(zero velocity, train average)``. This bench scores
forecasters that are told what no forecaster knows, with the protocol's own metric (``training.metrics``:
neck-centred 2D MPJPE of the forecast poses projected into the observing camera), on the validation and test
splits:

- ``train_average``: the protocol's baseline (the average training target pose, pelvis at x = y = 0);
- ``oracle_actions``: the true future actions, each step the average training target of its action (the
  baseline's frame);
- ``oracle_actions_last_place``: the true future actions, each step the action's mean pose in the body frame,
  placed at the last observed step's true 3D place and facing its true heading (the most a forecaster can
  know of where a person is: in ``markov`` the place and heading then walk at random);
- ``one_pose_last_place``: the same with one mean pose for every action (the true actions unused);
- ``oracle_actions_true_place``: the true actions at each forecast step's own true place and heading (only
  the pose within the action is unknown).

    .venv/bin/python bench/bench_forecast_behaviour_oracle.py [--script markov|stations]

Needs the CMU mocap (ROOMCAP_SHARED). Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from roomcap.forecast.lab.behaviour import data as bdata
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.model import BehaviourConfig


def body_frame(P: np.ndarray, pelvis: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N,J,3) in the viewer frame (z up) -> the same with the pelvis at x = y = 0 turned to
    heading 0, and each pose's heading (rad, ``data._facing``)."""
    heading = np.array([bdata._facing(x) for x in P])
    out = P.copy()
    out[..., :2] -= P[:, pelvis : pelvis + 1, :2]
    return np.einsum("nij,nkj->nki", np.stack([bdata._yaw(-h) for h in heading]), out), heading


def placed(pose: np.ndarray, heading: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Body-frame poses (N,J,3) turned to ``heading (N,)`` with the pelvis moved to ``xy (N,2)``."""
    out = np.einsum("nij,nkj->nki", np.stack([bdata._yaw(h) for h in heading]), pose)
    out[..., :2] += xy[:, None]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--script", choices=bdata.SCRIPTS, default="markov")
    args = ap.parse_args()
    t0 = time.perf_counter()
    cfg = BehaviourConfig(script=args.script, context="room" if args.script == "stations" else "camera")
    sp = T.load_splits(cfg, 0, cfg.joint_names)
    names, n_obs, m = sp.train.names, cfg.n_obs, cfg.m
    J, pelvis = len(names), names.index("pelvis")
    tr_acts = sp.train.acts[:, n_obs:].reshape(-1)
    tr_pose = sp.train.tgt_3d.reshape(-1, J, 3)
    A = len(bdata.ACTIONS)
    centred = tr_pose.copy()
    centred[..., :2] -= centred[:, pelvis : pelvis + 1, :2]  # train_average's frame
    mean_viewer = np.stack([centred[tr_acts == a].mean(0) for a in range(A)])
    body, _ = body_frame(tr_pose, pelvis)
    mean_body = np.stack([body[tr_acts == a].mean(0) for a in range(A)])
    pool = bdata.split_pool(bdata.load_pool())
    jidx = [bdata.JOINTS.index(n) for n in names]
    res: dict[str, dict] = {}
    for i, split in ((1, "val"), (2, "test")):  # load_splits' seeds: seed * 10 + i
        d = getattr(sp, split)
        S = len(d)
        comp = bdata.make_composite(pool[split], cfg.n_eval, n_obs + m, i, script=cfg.script)
        assert np.array_equal(comp.actions[:, : n_obs + m], d.acts), "the split was not rebuilt alike"
        # the last observed step's true 3D in the viewer frame (as prepare() makes the targets')
        und = np.stack([comp.rig[int(c)].undistort_px(comp.xy_px[s]) for s, c in enumerate(comp.cam)])
        g = T.anchors(
            *(np.stack([getattr(comp.rig[int(c)], k) for c in comp.cam]) for k in "KRt"), und[:, :n_obs]
        )
        last = np.einsum("sij,snj->sni", d.view.V, comp.xyz_m[:, n_obs - 1][:, jidx] - g[:, None])
        _, last_heading = body_frame(last, pelvis)
        fut = d.acts[:, n_obs:]  # (S,m)
        rep = np.repeat  # per forecast step: the last observed place and heading
        last_h, last_xy = rep(last_heading, m), rep(last[:, pelvis, :2], m, 0)
        true_pose = d.tgt_3d.reshape(-1, J, 3)
        _, true_h = body_frame(true_pose, pelvis)
        poses = {
            "train_average": np.broadcast_to(T.train_average(sp.train), (S, m, J, 3)),
            "oracle_actions": mean_viewer[fut],
            "oracle_actions_last_place": placed(mean_body[fut].reshape(-1, J, 3), last_h, last_xy),
            "one_pose_last_place": placed(np.broadcast_to(body.mean(0), (S * m, J, 3)), last_h, last_xy),
            "oracle_actions_true_place": placed(
                mean_body[fut].reshape(-1, J, 3), true_h, true_pose[:, pelvis, :2]
            ),
        }
        res[split] = {
            k: T.metrics(None, np.asarray(v).reshape(S, m, J, 3), d, n_obs)["mpjpe2d_px"]
            for k, v in poses.items()
        }
        zv = T.metrics(None, None, d, n_obs, px2d=T.zero_velocity_2d(d, m))["mpjpe2d_px"]
        res[split]["zero_velocity"] = zv
        res[split]["target_px"] = 0.9 * min(zv, res[split]["train_average"])
    for split, r in res.items():
        print(f"{args.script} {split} (2D px; target {r['target_px']:.1f}):")
        for k, v in r.items():
            if k != "target_px":
                print(f"  {k:28s} {v:6.1f}  ({v / r['train_average']:.3f} x train average)")
    print("BENCH " + json.dumps({"script": args.script, **res, "wall_s": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    main()
