"""Behaviour forecaster (Diller ch. 4): why the full model's 3D poses are judged fake (VALIDATION split).

Trains one variant with ``--set`` overrides (eq. 4.1, model selection on the validation objective as
``forecast behaviour train``) and reports on the validation sequences: 2D MPJPE (px), top-1, 3D MPJPE (mm,
diagnostic), Table 4.10's symmetry (mm), the bone lengths against the 3D database's (mean ratio and the
spread over poses, coefficient of variation), and the share the shipped quality classifier of the script
judges real, for the forecasts as they are and with each bone rescaled to the database's mean length
(directions kept: how much of the "fake" verdict the bone lengths alone explain). With ``--checkpoint`` it
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
from roomcap.forecast.behaviour import model as M
from roomcap.forecast.behaviour import quality as Q
from roomcap.forecast.behaviour import training as T
from roomcap.forecast.behaviour.cli import QUALITY_OF_SCRIPT


def pose_stats(P: np.ndarray, names, db_ref: np.ndarray, clf) -> dict:
    """Bone-length and quality figures of poses P (N,J,3) against database poses ``db_ref``."""
    b = M.bones(names)

    def blen(X):
        return np.linalg.norm(X[:, b[:, 0]] - X[:, b[:, 1]], axis=-1)

    L, Ldb = blen(P), blen(db_ref).mean(0)
    sk = M.Skeleton(b)
    sk.set_lengths(db_ref)
    fixed = sk(torch.from_numpy(P.astype(np.float32)), torch.zeros(len(P))).numpy()
    return {
        "symmetry_mm": T.symmetry(P, names)["symmetry_mm"],
        "bone_ratio_mean": float((L.mean(0) / Ldb).mean()),
        "bone_cv": float((L.std(0) / np.maximum(L.mean(0), 1e-9)).mean()),
        "quality_shipped_clf": T.share_real(clf, P, names),
        "quality_shipped_clf_db_bones": T.share_real(clf, fixed, names),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--checkpoint", default=None, help="score this checkpoint's pose models instead")
    ap.add_argument("--variant", default="full")
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
    qm = Q.load(QUALITY_OF_SCRIPT[cfg.script])
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
        r.update(pose_stats(ps.reshape(-1, len(names), 3), names, real_t, qm.clf))
        out["models"][n] = r
    out["wall_s"] = time.perf_counter() - t0
    for n, r in out["models"].items():
        print(n, {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()})
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
