"""The CMU 8-action benchmark (``forecast eval --protocol cmu8``) with the shipped DCT + MLP model
(``B.SHIPPED_MLP``): per horizon its MPJPE, the ratio to zero velocity and to the first shipped model
(``cmu8_dct_mlp.pt``) measured in the same run, and the ratio to LTD's published average; the evaluation's
wall time and the model's forecasts per second.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_forecast_cmu8.py

Needs ``$ROOMCAP_SHARED/data/motion/cmu-more/benchmark-cmu8`` (test/basketball_signal and
test/directing_traffic are missing there: the averages are over the other 6 actions). Ends with one line
``BENCH {json}``.
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch

from roomcap.forecast.lab import benchmark_cmu8 as B
from roomcap.forecast.lab import benchmark_cmu8_published as P
from roomcap.forecast.lab import cmu_more as C


def main() -> None:
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    first_ck = B.SHIPPED_MLP.with_name("cmu8_dct_mlp.pt")
    cks = [B.SHIPPED_MLP] + ([first_ck] if first_ck != B.SHIPPED_MLP and first_ck.is_file() else [])
    res = B.evaluate(mlp_checkpoints=cks)
    wall = time.perf_counter() - t0
    ours = res["models"][B.SHIPPED_MLP.stem]["mpjpe_mm"]
    zero = res["models"]["zero_velocity"]["mpjpe_mm"]
    first = res["models"][cks[-1].stem]["mpjpe_mm"]
    ltd = P.PUBLISHED["LTD (Mao et al. 2019)"]["mpjpe_mm"]
    print(f"actions {', '.join(res['actions'])}; missing: {', '.join(res['actions_missing'])}")
    print(f"ours: {B.SHIPPED_MLP.name}; first: {cks[-1].name}")
    print("horizon ms | ours | zero velocity | ours / zero | first | ours / first | LTD (pub.) | ours / LTD")
    for h, o, z, f, lt in zip(res["horizons_ms"], ours, zero, first, ltd, strict=True):
        r, lts = (f"{o / lt:.3f}", f"{lt:6.1f}") if lt else ("-", "     -")
        print(f"{h:>10} | {o:6.1f} | {z:6.1f} | {o / z:.3f} | {f:6.1f} | {o / f:.3f} | {lts} | {r}")
    model, _ = B.load_mlp(B.SHIPPED_MLP)
    obs = np.concatenate([w[:, : B.N_OBS] for w in B.test_set(C.benchmark_files()).windows.values()])
    obs = np.repeat(obs, 8, 0)
    t1 = time.perf_counter()
    B.mlp_forecast(model, obs)
    per_s = len(obs) / (time.perf_counter() - t1)
    print(f"evaluation wall {wall:.1f} s; {B.SHIPPED_MLP.stem} {per_s:.0f} forecasts/s (one thread)")
    bench = {
        "bench": "forecast_cmu8",
        "mpjpe_mm": ours,
        "zero_velocity_mm": zero,
        "ratio_to_zero": [o / z for o, z in zip(ours, zero, strict=True)],
        "first_model_mm": first,
        "ratio_to_first": [o / f for o, f in zip(ours, first, strict=True)],
        "ratio_to_ltd_1000ms": ours[-1] / ltd[-1],
        "actions": res["actions"],
        "wall_s": wall,
        "forecasts_per_s": per_s,
    }
    print("BENCH " + json.dumps(bench))


if __name__ == "__main__":
    main()
