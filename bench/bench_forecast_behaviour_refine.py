"""Behaviour forecaster: ch. 3's pose refinement (eq. 3.2) after decoding, a variant beyond ch. 4
(``forecast.lab.behaviour.refine``), for every model that outputs 3D poses, scored on the VALIDATION split
(or ``--split``) for a grid of settings: 2D MPJPE (px), the quality under one classifier, Table 4.10's
symmetry (mm) and 3D MPJPE (mm, diagnostic), raw and refined.

    .venv/bin/python bench/bench_forecast_behaviour_refine.py --checkpoint A.pt [B.pt ...] \
        --quality-classifier Q.pt [--split val] [--grid w_a=0.4,bones=first w_a=0,bones=database ...]

Needs the CMU mocap (ROOMCAP_SHARED). Torch on one thread. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from roomcap.core.cli import parse_sets
from roomcap.forecast.lab.behaviour import model as M
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour import refine as R
from roomcap.forecast.lab.behaviour import training as T

GRID = ("w_a=0.4,bones=first", "w_a=0,bones=first", "w_a=0.4,bones=database", "w_a=0,bones=database")


def scores(probs, poses, d, names, clf) -> dict:
    r = T.metrics(probs, poses, d, 3)
    P = poses.reshape(-1, len(names), 3)
    return {
        "mpjpe2d_px": r["mpjpe2d_px"],
        "quality3d": T.share_real(clf, P, names),
        "symmetry_mm": T.symmetry(P, names)["symmetry_mm"],
        "mpjpe3d_mm": r["mpjpe3d_mm"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", nargs="+", required=True)
    ap.add_argument("--quality-classifier", required=True)
    ap.add_argument("--split", choices=("val", "test"), default="val")
    ap.add_argument("--grid", nargs="*", default=list(GRID), metavar="KEY=VALUE,...")
    args = ap.parse_args()
    torch.set_num_threads(1)
    qm = Q.load(args.quality_classifier)
    out: dict = {"split": args.split, "runs": []}
    sp = None
    for path in args.checkpoint:
        gens, cfgs, _ = M.load_checkpoint(path)
        cfg = cfgs["full"]
        if sp is None:
            sp = T.load_splits(cfg, with_train=False)
        d = getattr(sp, args.split)
        names = d.names
        run: dict = {"checkpoint": path, "models": {}}
        true = d.tgt_3d.reshape(-1, len(names), 3)
        run["true_3d"] = {"quality3d": T.share_real(qm.clf, true, names)}
        for n, g in gens.items():
            if not cfgs[n].use_pose:
                continue
            _, ps = T.predict(g, cfgs[n], d)
            res = {"raw": scores(None, ps, d, names, qm.clf)}
            for spec in args.grid:
                rc = R.refine_config_from_dict(parse_sets(spec.split(",")))
                t0 = time.process_time()
                ref = R.refine(ps, names, rc, sp.db)
                res[spec] = {**scores(None, ref, d, names, qm.clf), "cpu_s": time.process_time() - t0}
            run["models"][n] = res
            for k, v in res.items():
                print(
                    f"{path} {n:10s} {k:24s} 2D {v['mpjpe2d_px']:.1f} px  quality {v['quality3d']:.3f}  "
                    f"symm {v['symmetry_mm']:.1f} mm  3D {v['mpjpe3d_mm']:.0f} mm",
                    flush=True,
                )
        print(f"{path} true_3d quality {run['true_3d']['quality3d']:.3f}")
        out["runs"].append(run)
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
