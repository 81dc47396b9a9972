"""Forecast protocol controls on the CMU test split: the baselines real / zero / const / slide
scored by the seed's protocol (NDMS database by activity incl. the query's own clip, and leave-clip-out), and
the same evaluation with every clip moved by 5 m: the largest change of any metric. Also the wall time of the
evaluation against the old single-pool database (all held-out clips as one group, the baseline of the
timing ratio).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_forecast_protocols.py [--max-windows 400]

Needs the CMU BVH under $ROOMCAP_SHARED/data/motion. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import train as T

SHIFT_M = np.array([5.0, 0.0, 0.0], np.float32)


def _models():
    return {
        "real": E.Real(),
        "zero": T.baseline("zero"),
        "const": T.baseline("const"),
        "slide": T.baseline("slide"),
    }


def _largest_change(a: dict, b: dict) -> dict:
    out = {}
    for name, m in a["models"].items():
        worst = 0.0
        for key, v in m.items():
            if key in ("wall_s", "rollout"):
                continue
            x = np.asarray(list(v.values()) if isinstance(v, dict) else v, float)
            w = b["models"][name][key]
            y = np.asarray(list(w.values()) if isinstance(w, dict) else w, float)
            if x.size:
                worst = max(worst, float(np.nanmax(np.abs(x - y))))
        out[name] = worst
    return out


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--max-windows", type=int, default=400)
    args = p.parse_args()
    clips = T.load_sources(["cmu"])
    _, _, te = T.split_clips(clips, 0)
    kw = dict(max_windows=args.max_windows, n_samples=1, n_boot=500)
    t0 = time.perf_counter()
    pooled = E.evaluate_single(_models(), te, activities={c.name: "all" for c in te}, **kw)
    t_pooled = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = E.evaluate_single(_models(), te, **kw)
    t_seed = time.perf_counter() - t0
    moved = [D.Clip(c.name, c.xyz_m + SHIFT_M, c.fps, c.skeleton) for c in te]
    res_moved = E.evaluate_single(_models(), moved, **kw)
    change = _largest_change(res, res_moved)
    print(f"{res['n_windows']} windows of {res['n_clips']} clips; leave-clip-out on {res['n_windows_loo']}")
    print(f"activities: {res['activities']}")
    print(
        "| baseline | ndms 0.4 / 1 / 2 / 4 s | ndms_loo 0.4 / 1 / 2 / 4 s | pooled ndms_loo 2 / 4 s "
        "| max change, 5 m |"
    )
    print("|---|---|---|---|---|")
    for name, r in res["models"].items():
        nd = " / ".join(f"{r['ndms_at'][t][0]:.3f}" for t in ("0.4", "1", "2", "4"))
        lo = " / ".join(f"{r['ndms_loo_at'][t][0]:.3f}" for t in ("0.4", "1", "2", "4"))
        po = " / ".join(f"{pooled['models'][name]['ndms_loo_at'][t][0]:.3f}" for t in ("2", "4"))
        print(f"| {name} | {nd} | {lo} | {po} | {change[name]:.1e} |")
    print(f"wall: seed protocol {t_seed:.1f} s, single pool {t_pooled:.1f} s")
    bench = {
        "n_windows": res["n_windows"],
        "n_windows_loo": res["n_windows_loo"],
        "ndms_2s": {k: r["ndms_at"]["2"][0] for k, r in res["models"].items()},
        "ndms_loo_2s": {k: r["ndms_loo_at"]["2"][0] for k, r in res["models"].items()},
        "ndms_loo_4s": {k: r["ndms_loo_at"]["4"][0] for k, r in res["models"].items()},
        "max_change_moved_5m": change,
        "wall_s": t_seed,
        "wall_s_single_pool": t_pooled,
        "wall_ratio_vs_single_pool": t_seed / t_pooled,
    }
    print("BENCH " + json.dumps(bench))


if __name__ == "__main__":
    main()
