"""Behaviour forecaster (Diller ch. 4): why the full model's 3D poses are judged fake (VALIDATION split).

Trains one variant with ``--set`` overrides (eq. 4.1, model selection on the validation objective as
``forecast behaviour train``) and reports on the validation sequences: 2D MPJPE (px), top-1, 3D MPJPE (mm,
diagnostic), Table 4.10's symmetry (mm), the bone lengths against the 3D database's (mean ratio and the
spread over poses, coefficient of variation), and the share the shipped quality classifier of the script
judges real (or ``--quality-classifier``'s), for the forecasts as they are and with each bone rescaled to the
database's mean length (directions kept: how much of the "fake" verdict the bone lengths alone explain, and
what that costs in 2D). With ``--checkpoint`` it
scores a trained checkpoint's pose models instead of training.

    .venv/bin/python bench/bench_forecast_behaviour_critic.py [--set KEY=VALUE ...] [--checkpoint FILE]

Needs the CMU mocap (ROOMCAP_SHARED). Torch on one thread. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import torch

from roomcap.core.cli import parse_sets
from roomcap.forecast.lab.behaviour import model as M
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.cli import QUALITY_OF_SCRIPT


def db_bones(P: np.ndarray, names, db_ref: np.ndarray) -> np.ndarray:
    """Poses P (...,J,3) with every bone at the database's mean length (directions and pelvis kept)."""
    sk = M.Skeleton(M.bones(names))
    sk.set_lengths(db_ref)
    X = torch.from_numpy(P.reshape(-1, len(names), 3).astype(np.float32))
    return sk(X, torch.zeros(len(X))).numpy().reshape(P.shape)


def pose_stats(P: np.ndarray, names, db_ref: np.ndarray, clf) -> dict:
    """Bone-length and quality figures of poses P (N,J,3) against database poses ``db_ref``."""
    b = M.bones(names)

    def blen(X):
        return np.linalg.norm(X[:, b[:, 0]] - X[:, b[:, 1]], axis=-1)

    L, Ldb = blen(P), blen(db_ref).mean(0)
    fixed = db_bones(P, names, db_ref)
    return {
        "symmetry_mm": T.symmetry(P, names)["symmetry_mm"],
        "bone_ratio_mean": float((L.mean(0) / Ldb).mean()),
        "bone_cv": float((L.std(0) / np.maximum(L.mean(0), 1e-9)).mean()),
        "quality": T.share_real(clf, P, names),
        "quality_db_bones": T.share_real(clf, fixed, names),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--checkpoint", default=None, help="score this checkpoint's pose models instead")
    ap.add_argument("--variant", default="full")
    ap.add_argument("--quality-classifier", default=None, help="default: the shipped one of the script")
    args = ap.parse_args()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    if args.checkpoint:
        gens, cfgs, _ = M.load_checkpoint(args.checkpoint)
        cfg = next(iter(cfgs.values()))
    else:
        cfg = dataclasses.replace(
            M.config_from_dict(parse_sets(args.set)) if args.set else M.BehaviourConfig(),
            variant=args.variant,
        )
    sp = T.load_splits(cfg, with_train=args.checkpoint is None)
    names = cfg.joint_names
    qm = Q.load(args.quality_classifier or QUALITY_OF_SCRIPT[cfg.script])
    _, real_t = Q.real_split(sp.db, names)
    out: dict = {"config": dataclasses.asdict(cfg), "models": {}}
    if not args.checkpoint:
        g, h = T.train(cfg, sp.train, sp.val, sp.db)
        gens, cfgs = {cfg.variant: g}, {cfg.variant: cfg}
        out["best_step"], out["train_wall_s"] = h.get("best_step"), h["train_wall_s"]
    true = sp.val.tgt_3d.reshape(-1, len(names), 3)
    out["models"]["true_3d"] = pose_stats(true, names, real_t, qm.clf)
    for n, g in gens.items():
        if not cfgs[n].use_pose:
            continue
        pr, ps = T.predict(g, cfgs[n], sp.val)
        r = T.metrics(pr if cfgs[n].use_action else None, ps, sp.val, cfg.n_obs)
        r = {k: r[k] for k in ("mpjpe2d_px", "top1", "mpjpe3d_mm")}
        fx = T.metrics(None, db_bones(ps, names, real_t), sp.val, cfg.n_obs)
        r["mpjpe2d_px_db_bones"], r["mpjpe3d_mm_db_bones"] = fx["mpjpe2d_px"], fx["mpjpe3d_mm"]
        r.update(pose_stats(ps.reshape(-1, len(names), 3), names, real_t, qm.clf))
        # the bones shrink as the forecast grows uncertain: the 2D MSE's mean of the possible futures
        steps = [pose_stats(ps[:, k], names, real_t, qm.clf) for k in range(ps.shape[1])]
        r["bone_ratio_by_step"] = [round(s["bone_ratio_mean"], 3) for s in steps]
        out["models"][n] = r
    out["wall_s"] = time.perf_counter() - t0
    for n, r in out["models"].items():
        print(n, {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()})
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
