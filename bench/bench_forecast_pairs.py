"""Two people together on held-out real takes (the CMU salsa pairs, ``clips.load_two_person_real``): NDMS
per person to 10 s, the partners' distance and facing angle against the real takes' 5-95 % range, SSCP
(``forecast.pairs``), for the checkpoints given and the baselines real / zero / const.

    OPENBLAS_NUM_THREADS=1 python bench/bench_forecast_pairs.py CKPT.pt [CKPT.pt ...] [--horizon-s 10] \
        [--samples 10]

Also MPJPE at 400 ms (mean over samples and best-of-k) and NDMS with the window's own take left out of D;
baselines real / zero / const / slide.

A checkpoint trained or selected on a held-out take is refused. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import pairs
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.clips import load_two_person_real
from roomcap.forecast.lab.protocol import render


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("checkpoints", nargs="*")
    p.add_argument("--horizon-s", type=float, default=10.0)
    p.add_argument("--stride", type=int, default=50)
    p.add_argument("--samples", type=int, default=1, help="samples per stochastic model (best-of-k MPJPE)")
    p.add_argument("--out", default="")
    args = p.parse_args()
    torch.set_num_threads(1)
    data = load_two_person_real()
    held_out = {c.name for c in data.test}
    models: dict = {n: T.baseline(n) for n in ("zero", "const", "slide")}
    models = {"real": E.Real(), **models}
    for ck in args.checkpoints:
        m, meta = T.load_checkpoint(ck, skeleton="body19")
        used = set(meta["extra"].get("train_clips", [])) | set(meta["extra"].get("val_clips", []))
        if used & held_out:
            raise SystemExit(f"{ck} was trained or selected on held-out takes {sorted(used & held_out)}")
        models[Path(ck).stem] = m
    res = pairs.evaluate_pairs(
        models,
        data.test,
        n_pred=int(round(args.horizon_s * 25)),
        stride=args.stride,
        activities=data.activities,
        n_samples=args.samples,
    )
    print(render(res))
    for name, r in res["models"].items():
        print(f"{name}: wall {r['wall_s']:.1f} s")
    if args.out:
        Path(args.out).write_text(json.dumps(res))
    bench = {
        "n_windows": res["n_windows"],
        "takes": res["takes"],
        "real_range": res["real_range"],
        "ndms_at": {k: r["ndms_at"] for k, r in res["models"].items()},
        "ndms_loo_at": {k: r["ndms_loo_at"] for k, r in res["models"].items()},
        "mpjpe_400_mm": {k: 1000 * r["mpjpe"][9] for k, r in res["models"].items()},
        "mpjpe_best_of_k_400_mm": {k: 1000 * r["mpjpe_best_of_k"][9] for k, r in res["models"].items()},
        "distance_in_range": {k: r["distance_in_range"] for k, r in res["models"].items()},
        "facing_in_range": {k: r["facing_in_range"] for k, r in res["models"].items()},
        "sscp_jsd": {k: r["sscp_jsd"] for k, r in res["models"].items()},
        "wall_s": res["wall_s"],
    }
    print("BENCH " + json.dumps(bench))


if __name__ == "__main__":
    main()
