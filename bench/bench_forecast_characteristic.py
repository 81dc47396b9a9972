"""Characteristic-pose forecaster benchmark (Diller ch. 3): training step and sampling cost on this CPU.

Process CPU time (``time.process_time``) with torch on one thread by default, random inputs in the default
config (16^3 grid, N = 10, body19), so it needs no mocap. Sampling: k = 10 hypotheses for one observation,
with and without the pose refinement of eq. 3.2. With ``--eval``, also the sec. 3.6 figures of the shipped
checkpoint on the CMU test split (needs the mocap).

    .venv/bin/python bench/bench_forecast_characteristic.py [--steps 10] [--threads 1] [--eval]

Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from roomcap.forecast.lab import characteristic as C
from roomcap.forecast.lab.characteristic.cli import as_results
from roomcap.forecast.lab.protocol import render


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--eval", action="store_true", help="also evaluate the shipped checkpoint (test split)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = C.CharConfig()
    net, _ = C.build_models(cfg)
    J = net.n_joints
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(cfg.batch, cfg.n_obs, J, 3, generator=g) * 0.3
    tgt = torch.randn(cfg.batch, J, 3, generator=g) * 0.3
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    net.train()
    for i in range(args.steps + 1):
        if i == 1:  # first step is warm-up
            c0 = time.process_time()
        terms = net.loss(obs, tgt, n_rest=cfg.n_rest_train, generator=g)
        opt.zero_grad()
        terms["loss"].backward()
        opt.step()
    step_s = (time.process_time() - c0) / args.steps
    net.eval()
    one = obs[:1]
    net.sample(one, cfg.k, refine=False, generator=g)  # warm-up
    c0 = time.process_time()
    net.sample(one, cfg.k, refine=False, generator=g)
    sample_raw = time.process_time() - c0
    c0 = time.process_time()
    net.sample(one, cfg.k, refine=True, refine_iters=cfg.refine_iters, generator=g)
    sample_ref = time.process_time() - c0
    res = {
        "threads": args.threads,
        "batch": cfg.batch,
        "grid": cfg.grid,
        "params": sum(p.numel() for p in net.parameters()),
        "train_step_cpu_s": round(step_s, 4),
        "train_steps_per_cpu_s": round(1 / step_s, 3),
        "sample_k10_cpu_s": round(sample_raw, 4),
        "sample_k10_refined_cpu_s": round(sample_ref, 4),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    print(f"training step (batch {cfg.batch}, {cfg.n_rest_train} rest joints): {step_s:.3f} s CPU")
    print(f"sampling k = {cfg.k} for one observation: {sample_raw:.3f} s CPU, refined {sample_ref:.3f} s CPU")
    if args.eval:
        net, det, meta = C.load_checkpoint(C.SHIPPED, skeleton="body19")
        data = C.load_cmu_labelled(meta["fps"])
        ev = C.evaluate(net, det, meta["avg_pose"], data.test, meta["config"])
        print(render(as_results(ev)))
        res["test"] = {k: round(v["mpjpe"], 4) for k, v in ev["methods"].items()}
        res["test_diversity"] = round(ev["methods"]["ours"]["diversity"], 4)
        res["test_windows"] = ev["n_windows"]
    print("BENCH " + json.dumps(res))


if __name__ == "__main__":
    main()
