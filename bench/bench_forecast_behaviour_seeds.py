"""Behaviour forecaster (Diller ch. 4): several training seeds per model, scored alike, with their spread, and
the paired test of full against action only in top-1.

Each ``--checkpoint`` is one training seed (``forecast behaviour train --set ... seed=S``, every variant in
one file, or merged with ``forecast behaviour merge``); every one is scored on ``--split`` with
``training.evaluate_all`` under one quality classifier (``--quality-classifier``, the pooled one of
``forecast behaviour quality``), so the figures are those of ``forecast behaviour eval``. Per model: the
mean, standard deviation and range over the seeds of 2D MPJPE (px), quality, symmetry (mm), top-1, top-3 and
3D MPJPE (mm, diagnostic). Paired test: per seed, full minus action only in top-1 on the same sequences,
with a 95 % interval from a bootstrap that resamples whole sequences (each sequence's M steps together).

    .venv/bin/python bench/bench_forecast_behaviour_seeds.py --checkpoint A.pt B.pt ... \
        --quality-classifier Q.pt [--split val|test] [--refine]

Needs the CMU mocap (ROOMCAP_SHARED). Torch on one thread. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from roomcap.forecast.lab.behaviour import model as M
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour import refine as R
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.protocol import render

KEYS = ("mpjpe2d_px", "quality3d", "symmetry_mm", "top1", "top3", "mpjpe3d_mm")
REFINED = ("mpjpe2d_px_refined", "refine_cost_px", "quality3d_refined", "symmetry_mm_refined")


def paired_top1(a: np.ndarray, b: np.ndarray, gt: np.ndarray, n_boot: int = 2000, seed: int = 0) -> dict:
    """Top-1 of probabilities a minus b (S,m,A) on targets gt (S,m): the difference and its 95 % interval
    from a bootstrap over sequences."""
    d = ((a.argmax(-1) == gt).mean(1) - (b.argmax(-1) == gt).mean(1)).astype(np.float64)
    rng = np.random.default_rng(seed)
    boots = d[rng.integers(len(d), size=(n_boot, len(d)))].mean(1)
    lo, hi = np.percentile(boots, [2.5, 97.5])
    return {"diff": float(d.mean()), "ci95": [float(lo), float(hi)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", nargs="+", required=True)
    ap.add_argument("--quality-classifier", required=True)
    ap.add_argument("--split", choices=("val", "test"), default="val")
    ap.add_argument(
        "--refine", action="store_true", help="also the figures after ch. 3's pose refinement (its defaults)"
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    qm = Q.load(args.quality_classifier)
    runs, paired = [], []
    sp = None
    for path in args.checkpoint:
        gens, cfgs, extra = M.load_checkpoint(path)
        cfg = cfgs["full"]
        if sp is None:
            sp = T.load_splits(cfg, with_train=False)
        d = getattr(sp, args.split)
        res = T.evaluate_all(
            gens,
            cfgs,
            extra,
            sp.val,
            d,
            sp.db,
            quality_clf=(qm.clf, qm.joints),
            refine=R.RefineConfig() if args.refine else None,
        )
        runs.append({"checkpoint": path, "seed": cfg.seed, "models": res["models"]})
        if "action_only" in gens:
            pa = T.predict(gens["full"], cfg, d)[0]
            pb = T.predict(gens["action_only"], cfgs["action_only"], d)[0]
            paired.append({"seed": cfg.seed, **paired_top1(pa, pb, d.acts[:, cfg.n_obs :])})
        print(path, "seed", cfg.seed)
        print(render(T.as_results(res)))
        ceiling = res.get("ceiling_top1")
    summary: dict = {}
    for n in runs[0]["models"]:
        summary[n] = {}
        for k in KEYS + REFINED:
            v = [r["models"][n].get(k) for r in runs if n in r["models"]]
            v = np.array([x for x in v if x is not None], np.float64)
            if len(v):
                summary[n][k] = {
                    "mean": float(v.mean()),
                    "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                    "min": float(v.min()),
                    "max": float(v.max()),
                    "n": len(v),
                }
    print(f"\n{args.split}, {len(runs)} seeds: mean +- sd [min, max]")
    for n, s in summary.items():
        print(
            f"{n:<14} "
            + "  ".join(
                f"{k} {v['mean']:.3f}+-{v['sd']:.3f} [{v['min']:.3f},{v['max']:.3f}]" for k, v in s.items()
            )
        )
    for p in paired:
        print(
            f"top-1 full - action only, seed {p['seed']}: {p['diff']:+.4f} (95 % {p['ci95'][0]:+.4f}, "
            f"{p['ci95'][1]:+.4f})"
        )
    print(
        "BENCH "
        + json.dumps(
            {
                "split": args.split,
                "runs": runs,
                "summary": summary,
                "paired_top1": paired,
                "ceiling_top1": ceiling,
            }
        )
    )


if __name__ == "__main__":
    main()
