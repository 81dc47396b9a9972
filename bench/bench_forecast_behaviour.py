"""Behaviour forecaster benchmark (Diller ch. 4): the cost of a training step (generator rollout over M steps
plus the Wasserstein critic with its gradient penalty) and of one person's forecast, on this CPU; with
``--results`` the Table 4.1 ratios of an evaluation (``forecast behaviour eval --out results.json``) against
the baselines measured in the same run.

Process CPU time (``time.process_time``), torch on one thread by default, random inputs in the default config
(body19, n_obs 3, M 5), so it needs no mocap.

    .venv/bin/python bench/bench_forecast_behaviour.py [--steps 10] [--threads 1] [--results results.json]
        [--set KEY=VALUE ...]   (config overrides as in ``forecast behaviour train --set``)
        [--ceilings [--quality-classifier FILE]]

With ``--ceilings`` (needs the CMU mocap; about a minute) also what the composite data of the config's
``script`` allow: the top-1/top-3 accuracy of the best possible forecaster (Fig. 4.3's ceiling) from the
labels alone (forward filtering over the script's hidden states, ``data.chain_forecast``) and from labels and
place (the hidden state of the last observed step known; for ``script=markov`` the two are one, the state
being the label), and the 3D quality of the test sequences' true 3D poses: under the seed's metric (the
share the once-trained classifier ``--quality-classifier`` judges real, ``forecast behaviour quality``) and
under the per-method variant (a "method" whose val predictions, the classifier's fakes, are the val
sequences' true 3D).

Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from roomcap.core.cli import parse_sets
from roomcap.forecast.lab.behaviour import data as bdata
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.cli import QUALITY_OF_SCRIPT
from roomcap.forecast.lab.behaviour.data import ACTIONS, JOINTS
from roomcap.forecast.lab.behaviour.model import BehaviourConfig, build, config_from_dict, rollout
from roomcap.forecast.lab.behaviour.quality import load as load_quality
from roomcap.forecast.lab.behaviour.training import critic_input


def ceilings(cfg: BehaviourConfig, quality_classifier=None) -> dict:
    """The best possible top-1/top-3 per step of the config's script on the test split, from the labels alone
    and from labels and place, and the two qualities of the truth."""
    sp = T.load_splits(cfg, 0, JOINTS, with_train=False)
    d, n_obs = sp.test, cfg.n_obs
    ch = bdata.script_chain(cfg.script)
    labels = T.metrics(bdata.chain_forecast(ch, d.acts[:, :n_obs], cfg.m), None, d, n_obs)
    place = T.ceiling_top1(d, cfg.script, n_obs, cfg.m)  # what `forecast behaviour eval` reports
    assert place is not None
    top1, top3 = labels["top1_by_step"], labels["top3_by_step"]
    p1 = place["ceiling_top1_by_step"]
    real_v, real_t = sp.db[0::2], sp.db[1::2]
    J = len(JOINTS)
    fakes = np.concatenate([T.perturbed(real_v, JOINTS, 0), sp.val.tgt_3d.reshape(-1, J, 3)])
    clf = T.quality_classifier(real_v, fakes.astype(np.float32), JOINTS, 0)
    q = T.quality(clf, real_t, sp.test.tgt_3d.reshape(-1, J, 3), JOINTS, 0)
    seed_clf = load_quality(quality_classifier or QUALITY_OF_SCRIPT[cfg.script])
    qs = T.share_real(seed_clf.clf, sp.test.tgt_3d.reshape(-1, J, 3), JOINTS)
    return {
        "bayes_top1_by_step": top1,
        "bayes_top1": float(np.mean(top1)),
        "bayes_top3": float(np.mean(top3)),
        "script": cfg.script,
        "bayes_place_top1_by_step": p1,
        "bayes_place_top1": float(np.mean(p1)),
        "bayes_place_top3": place["ceiling_top3"],
        "quality3d_of_true_3d": qs,
        "quality3d_per_method_of_true_3d": q,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--results", default=None, help="an eval results.json to report ratios from")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    ap.add_argument("--ceilings", action="store_true", help="the data's Bayes top-1 and the truth's quality")
    ap.add_argument(
        "--quality-classifier", default=None, help="the truth's quality's classifier (default: the script's)"
    )
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
    room = torch.randn(B, 4, generator=g)  # read only with context=room
    og = torch.optim.Adam(gen.parameters(), lr=cfg.lr)
    oc = torch.optim.Adam(critic.parameters(), lr=cfg.lr)
    for i in range(args.steps + 1):
        if i == 1:  # first step is warm-up
            c0 = time.process_time()
        lg, P = rollout(gen, feats, acts, seen, c, cfg.m, room=room)
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
            rollout(gen, feats[:1], acts[:1], seen[:1], c[:1], cfg.m, room=room[:1])
        one_ms = (time.process_time() - c0) / 20 * 1000
    out = {
        "train_step_cpu_s": step_s,
        "batch": B,
        "forecast_one_person_cpu_ms": one_ms,
        "m": cfg.m,
        "n_critic": cfg.n_critic,
        "bone_lengths": cfg.bone_lengths,
        "context": cfg.context,
    }
    print(f"training step (batch {B}, M = {cfg.m}, {cfg.n_critic} critic step(s) + GP): {step_s:.3f} s CPU")
    print(f"one person's forecast (M = {cfg.m} steps): {one_ms:.2f} ms CPU")
    if args.results:
        with open(args.results, encoding="utf-8") as fh:
            res = json.load(fh)["models"]
        full = res["full"]

        def ratio(key: str, other: str):  # None where the results lack the model or the figure
            a, b = full.get(key), res.get(other, {}).get(key)
            return None if a is None or not b else a / b

        ratios = {
            "mpjpe2d_full_over_zero_velocity": ratio("mpjpe2d_px", "zero_velocity"),
            "mpjpe2d_full_over_train_average": ratio("mpjpe2d_px", "train_average"),
            "top1_full_over_action_only": ratio("top1", "action_only"),
            "mpjpe3d_full_over_train_average": ratio("mpjpe3d_mm", "train_average"),
            "quality3d_full": full["quality3d"],
            "quality3d_per_method_full": full.get("quality3d_per_method"),
            # Table 4.10's check: the target is at most 0.5
            "symmetry_full_over_action_2d": ratio("symmetry_mm", "action_2d"),
        }
        for k, v in ratios.items():
            print(f"{k}: " + ("-" if v is None else f"{v:.3f}"))
        out.update(ratios)
    if args.ceilings:
        ce = ceilings(cfg, args.quality_classifier)
        for what, k in (("labels alone", "bayes"), ("labels and place", "bayes_place")):
            print(
                f"best possible top-1 by step from {what} (script {cfg.script}, test split): "
                + " / ".join(f"{v:.1%}" for v in ce[f"{k}_top1_by_step"])
                + f"; overall {ce[f'{k}_top1']:.1%} (top-3 {ce[f'{k}_top3']:.1%})"
            )
        print(
            f"3D quality of the true 3D poses: {ce['quality3d_of_true_3d']:.2f} (seed's metric), "
            f"{ce['quality3d_per_method_of_true_3d']:.2f} (per-method variant)"
        )
        out.update(ce)
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
