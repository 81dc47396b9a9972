"""Checkpoints scored on the VALIDATION split (never the test split) with the trainer's own selection probe
(``forecast.selection.Validator``: observe 2 s, forecast 4 s at 25 Hz; NDMS with D = the validation clips of
the window's activity, own clip included, as the evaluation's ``ndms``): the figure checkpoints are chosen
by. Social Diffusion is rolled out as the model allows (``predict.diffusion_rollout``: one pass,
or chained windows for models bound to their window); the rollout and the sampling time are printed, and
the GRU's time is the baseline of the timing ratio when a GRU checkpoint is given.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_forecast_validation.py CKPT [CKPT ...] \
        [--windows 400 --stride 5 --samples 10 --seed 0] [--data cmu-all]

``--data cmu-all``: the validation clips of all one-person CMU data (``forecast.clips.load_one_person_all``,
as ``forecast train --data cmu-all`` selects on); the trainer's own probe is ``--windows 48 --stride 10
--samples 4``.

Needs the CMU BVH under $ROOMCAP_SHARED/data/motion. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.selection import VAL_N_PRED, Validator
from roomcap.forecast.runtime.predict import diffusion_rollout


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("checkpoints", nargs="+")
    p.add_argument("--windows", type=int, default=400)
    p.add_argument("--stride", type=int, default=5)
    p.add_argument("--samples", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data", choices=("cmu", "cmu-all"), default="cmu")
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.data == "cmu-all":
        from roomcap.forecast.lab.clips import load_one_person_all

        va = load_one_person_all().val
    else:
        clips = T.load_sources(["cmu"])
        _, va, _ = T.split_clips(clips, 0)
    v = Validator(va, n_samples=args.samples, max_windows=args.windows, stride=args.stride, seed=args.seed)
    print(f"{len(v.x)} validation windows of {len(va)} clips, {args.samples} samples, seed {args.seed}")
    print("| checkpoint | rollout | ndms 2-4 s | ndms 2/3 s, clips weighted equally | MPJPE 0-1 s | s |")
    print("|---|---|---|---|---|---|")
    out: dict = {}
    for ck in args.checkpoints:
        model, _ = T.load_checkpoint(ck)
        ro = diffusion_rollout(model, VAL_N_PRED) if model.kind == "social_diffusion" else "-"
        t0 = time.perf_counter()
        r = v(model)
        dt = time.perf_counter() - t0
        name = Path(ck).stem
        out[name] = {**r, "rollout": ro, "wall_s": dt}
        print(
            f"| {name} | {ro} | {r['ndms_2_4']:.4f} | {r['ndms_2_3']:.4f} | {1000 * r['mpjpe_0_1']:.0f} mm "
            f"| {dt:.1f} |"
        )
    gru = [k for k in out if k.startswith("gru")]
    bench = {"data": args.data, "n_windows": len(v.x), "samples": args.samples, "seed": args.seed}
    bench["models"] = out
    if gru:
        bench["wall_ratio_vs_" + gru[0]] = {k: r["wall_s"] / out[gru[0]]["wall_s"] for k, r in out.items()}
    print("BENCH " + json.dumps(bench))


if __name__ == "__main__":
    main()
