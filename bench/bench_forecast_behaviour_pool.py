"""Behaviour forecaster (Diller ch. 4): one training seed of every variant AND the pooled quality classifier
from the same runs, in one pass (the machine allows one training at a time).

``forecast behaviour quality`` trains separate snapshot runs (no model selection) and ``forecast behaviour
train`` the models (selection on the validation objective). With one config and seed both runs follow the same
trajectory (one random stream, ``training._fit_state``), so here each variant is trained once: snapshots of
its predictions on training sequences every ``--every`` steps (the classifier's fake pool, sec. 4.7.7) and the
state with the lowest validation objective kept (``training.train``'s rule). Writes the checkpoint (as
``forecast behaviour train --eval-split none``) and, with ``--quality-out``, the classifier (as ``forecast
behaviour quality``: database even frames against the pooled snapshots of full, pose_only, action_2d and the
train average's running mean, each source weighing alike).

    .venv/bin/python bench/bench_forecast_behaviour_pool.py --out B.pt [--quality-out Q.pt] \
        [--variants full,action_only,pose_only,action_2d] [--set KEY=VALUE ...]

Needs the CMU mocap (ROOMCAP_SHARED). Torch on one thread. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import time

import numpy as np
import torch

from roomcap.core.cli import parse_sets
from roomcap.forecast.lab.behaviour import model as M
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour import training as T


def train_with_snapshots(cfg, sp, every: int, per_snapshot: int):
    """``training.train`` with ``quality.snapshot_poses``'s snapshots taken along the way."""
    f = T._fit_state(cfg, sp.db)
    vb = T.to_torch(sp.val, np.arange(len(sp.val)), cfg.n_obs)
    rng = np.random.default_rng(cfg.seed)
    J = len(cfg.joint_names)
    snaps = []

    def snap(step):
        f.gen.eval()
        idx = rng.choice(len(sp.train), min(per_snapshot, len(sp.train)), replace=False)
        snaps.append((step, T.predict(f.gen, cfg, sp.train.take(idx))[1].reshape(-1, J, 3)))

    if cfg.use_pose:
        snap(0)
    hist: dict = {"val": []}
    best, best_state = np.inf, copy.deepcopy(f.gen.state_dict())
    t0 = time.perf_counter()
    for step in range(1, cfg.steps + 1):
        T._generator_step(f, sp.train)
        if cfg.use_pose and step % every == 0:
            snap(step)
        if step % cfg.eval_every == 0 or step == cfg.steps:
            v = T._validate(f, vb, step, time.perf_counter() - t0)
            hist["val"].append(v)
            if v["objective"] < best:
                best, best_state = v["objective"], copy.deepcopy(f.gen.state_dict())
                hist["best_step"] = step
    f.gen.load_state_dict(best_state)
    f.gen.eval()
    hist["train_wall_s"] = time.perf_counter() - t0
    return f.gen, hist, snaps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--quality-out", default=None)
    ap.add_argument("--variants", default="full,action_only,pose_only,action_2d")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--every", type=int, default=200)
    ap.add_argument("--per-snapshot", type=int, default=625)
    ap.add_argument("--clf-steps", type=int, default=4000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    base = M.config_from_dict(parse_sets(args.set)) if args.set else M.BehaviourConfig()
    sp = T.load_splits(base, 0, base.joint_names)
    gens, cfgs, hists, sources = {}, {}, {}, {}
    for v in [s.strip() for s in args.variants.split(",") if s.strip()]:
        cfg = dataclasses.replace(base, variant=v)
        gens[v], hists[v], snaps = train_with_snapshots(cfg, sp, args.every, args.per_snapshot)
        cfgs[v] = cfg
        if v in Q.POOL_VARIANTS:
            sources[v] = snaps
        print(f"{v}: best step {hists[v].get('best_step')}, {hists[v]['train_wall_s']:.0f} s", flush=True)
    extra = {
        "action_freq": T.action_frequencies(sp.train, base.n_obs).tolist(),
        "avg_pose": T.train_average(sp.train).tolist(),
        "history": hists,
        "command": "bench_forecast_behaviour_pool.py --set " + " ".join(args.set),
    }
    M.save_checkpoint(args.out, gens, cfgs, extra)
    out = {"checkpoint": args.out, "best_step": {v: h.get("best_step") for v, h in hists.items()}}
    if args.quality_out and sources:
        names = base.joint_names
        sources["train_average"] = Q.train_average_snapshots(base, sp.train, args.every)
        fake, pooled = Q.pool_fakes(sources, seed=base.seed)
        real, held = Q.real_split(sp.db, names)
        q = Q.fit(real, fake, names, seed=base.seed, steps=args.clf_steps)
        checks = {"database_held_out": T.share_real(q.clf, held, names)}
        checks.update(
            {f"{v}_step{s[-1][0]}": T.share_real(q.clf, s[-1][1], names) for v, s in sources.items()}
        )
        q.meta.update(
            variants=[v for v in sources if v != "train_average"],
            baselines=["train_average"],
            sources=pooled,
            config=dataclasses.asdict(base),
            share_judged_real=checks,
            command="bench_forecast_behaviour_pool.py --set " + " ".join(args.set),
        )
        Q.save(args.quality_out, q)
        out["quality_checks"] = checks
        print("classifier:", {k: round(v, 3) for k, v in checks.items()})
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
