"""Behaviour forecaster benchmark (Diller ch. 4): the cost of a training step (generator rollout over M steps
plus the Wasserstein critic with its gradient penalty) and of one person's forecast, on this CPU; with
``--results`` the Table 4.1 ratios of an evaluation (``forecast behaviour eval --out results.json``) against
the baselines measured in the same run.

Process CPU time (``time.process_time``), torch on one thread by default, random inputs in the default config
(body19, n_obs 3, M 5), so it needs no mocap.

    .venv/bin/python bench/bench_forecast_behaviour.py [--steps 10] [--threads 1] [--results results.json]
        [--set KEY=VALUE ...]   (config overrides as in ``forecast behaviour train --set``)

Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from core.cli import parse_sets
from forecast.behaviour.data import ACTIONS
from forecast.behaviour.model import build, config_from_dict, rollout
from forecast.behaviour.training import critic_input


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--results", default=None, help="an eval results.json to report ratios from")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = config_from_dict(parse_sets(args.set))
    gen, critic = build(cfg)
    B, N, J, A = cfg.batch, cfg.n_obs, len(cfg.joint_names), len(ACTIONS)
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(B, N, J, 2, generator=g) * 0.4
    seen = torch.ones(B, N, J, dtype=torch.bool)
    acts = torch.randint(A, (B, N), generator=g)
    c = torch.tensor([[0.0, -4.0, 2.2]]).repeat(B, 1)
    og = torch.optim.Adam(gen.parameters(), lr=cfg.lr)
    oc = torch.optim.Adam(critic.parameters(), lr=cfg.lr)
    for i in range(args.steps + 1):
        if i == 1:  # first step is warm-up
            c0 = time.process_time()
        lg, P = rollout(gen, feats, acts, seen, c, cfg.m)
        fake = critic_input(P.reshape(-1, J, 3), cfg.joint_names.index("pelvis"))[:B]
        for _ in range(cfg.n_critic):
            mix = fake.detach().clone().requires_grad_(True)
            grad = torch.autograd.grad(critic(mix).sum(), mix, create_graph=True)[0]
            lc = critic(fake.detach()).mean() + ((grad.reshape(B, -1).norm(dim=1) - 1) ** 2).mean()
            oc.zero_grad()
            lc.backward()
            oc.step()
        loss = torch.nn.functional.cross_entropy(lg.reshape(-1, A), torch.zeros(B * cfg.m, dtype=torch.long))
        loss = loss - critic(fake).mean() + P.square().mean()
        og.zero_grad()
        loss.backward()
        og.step()
    step_s = (time.process_time() - c0) / args.steps
    gen.eval()
    with torch.no_grad():
        c0 = time.process_time()
        for _ in range(20):
            rollout(gen, feats[:1], acts[:1], seen[:1], c[:1], cfg.m)
        one_ms = (time.process_time() - c0) / 20 * 1000
    out = {
        "train_step_cpu_s": step_s,
        "batch": B,
        "forecast_one_person_cpu_ms": one_ms,
        "m": cfg.m,
        "n_critic": cfg.n_critic,
        "bone_lengths": cfg.bone_lengths,
    }
    print(f"training step (batch {B}, M = {cfg.m}, {cfg.n_critic} critic step(s) + GP): {step_s:.3f} s CPU")
    print(f"one person's forecast (M = {cfg.m} steps): {one_ms:.2f} ms CPU")
    if args.results:
        with open(args.results, encoding="utf-8") as fh:
            res = json.load(fh)["models"]
        full = res["full"]
        ratios = {
            "mpjpe2d_full_over_zero_velocity": full["mpjpe2d_px"] / res["zero_velocity"]["mpjpe2d_px"],
            "mpjpe2d_full_over_train_average": full["mpjpe2d_px"] / res["train_average"]["mpjpe2d_px"],
            "top1_full_over_action_only": full["top1"] / res["action_only"]["top1"],
            "mpjpe3d_full_over_train_average": full["mpjpe3d_mm"] / res["train_average"]["mpjpe3d_mm"],
            "quality3d_full": full["quality3d"],
        }
        for k, v in ratios.items():
            print(f"{k}: {v:.3f}")
        out.update(ratios)
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
