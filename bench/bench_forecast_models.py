"""Forecast benchmark: training steps/s and sampling time per forecast second, per model, on this CPU.

Uses the default (small) configs and toy walking clips (no mocap needed), torch with 1 thread by default.
Sampling: one scene of two people (single-person models forecast each), one sample, 25 Hz; Social Diffusion
both with the seed's sampler (T reverse steps, fresh noise, eq. 7.6) and the few-step DDIM option.

    .venv/bin/python bench/bench_forecast_models.py [--train-steps 15] [--horizon-s 2] [--threads 1]

Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.toy import walker
from roomcap.forecast.runtime.predict import forecast_world


def _clips():
    return [
        D.Clip(f"w{i}", walker(300, phase=i, speed_mps=0.8 + 0.1 * i, heading_rad=i, turn_rps=0.05 * i), 25.0)
        for i in range(8)
    ]


def train_rate(kind: str, clips, steps: int) -> float:
    cfg = T.config_from_dict(kind, {"steps": steps + 3})
    _, hist = T.train(kind, clips, cfg)
    return hist["steps_per_s"]


def sample_time_per_s(model, obs, horizon_s: float, reps: int = 1, **kw) -> float:
    n_pred = int(round(horizon_s * 25))
    forecast_world(model, obs, None, min(n_pred, 5), 1, **kw)  # warm-up
    t0 = time.perf_counter()
    for _ in range(reps):
        forecast_world(model, obs, None, n_pred, 1, **kw)
    return (time.perf_counter() - t0) / reps / horizon_s


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--train-steps", type=int, default=15)
    ap.add_argument("--horizon-s", type=float, default=2.0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    clips = _clips()
    scene = np.stack([walker(50), walker(50, start=(2, 0), heading_rad=2.0)], 1)[None]  # (1,50,2,J,3)
    res: dict = {
        "threads": args.threads,
        "horizon_s": args.horizon_s,
        "loadavg_1min_start": os.getloadavg()[0],
    }
    for kind in ("zero_velocity", "constant_velocity"):
        res[f"{kind}_sample_s_per_forecast_s"] = sample_time_per_s(T.baseline(kind), scene, args.horizon_s, 5)
    for kind in ("gru", "intention", "social_diffusion"):
        rate = train_rate(kind, clips, args.train_steps)
        res[f"{kind}_train_steps_per_s"] = rate
        cfg = T.config_from_dict(kind)
        model = T.build_model(kind, cfg, 19)
        if kind == "intention":
            model.centres.normal_()
        obs = scene[:, -cfg.n_obs :]
        if kind == "social_diffusion":
            res["social_diffusion_fewstep_sample_s_per_forecast_s"] = sample_time_per_s(
                model, obs, args.horizon_s, steps=cfg.sample_steps, eta=0.0
            )
            res["social_diffusion_fewstep_steps"] = cfg.sample_steps
            res["social_diffusion_full_sample_s_per_forecast_s"] = sample_time_per_s(
                model, obs, 1.0, steps=cfg.T, eta=1.0
            )
            res["social_diffusion_full_steps"] = cfg.T
        else:
            res[f"{kind}_sample_s_per_forecast_s"] = sample_time_per_s(model, obs, args.horizon_s, 2)
        print(f"{kind}: {rate:.2f} train steps/s (batch {cfg.batch})", flush=True)
    base = res["constant_velocity_sample_s_per_forecast_s"]
    for k in list(res):
        if k.endswith("_sample_s_per_forecast_s"):
            print(
                f"{k[: -len('_sample_s_per_forecast_s')]:>26}: {1000 * res[k]:9.2f} ms per forecast second "
                f"({res[k] / base:8.1f}x constant velocity)"
            )
    res["diffusion_fewstep_speedup"] = (
        res["social_diffusion_full_sample_s_per_forecast_s"]
        / res["social_diffusion_fewstep_sample_s_per_forecast_s"]
    )
    print(
        f"few-step ({res['social_diffusion_fewstep_steps']}) vs seed sampler "
        f"({res['social_diffusion_full_steps']} steps): {res['diffusion_fewstep_speedup']:.1f}x faster"
    )
    res["loadavg_1min_end"] = os.getloadavg()[0]  # figures are per this (shared) CPU's load
    print("BENCH " + json.dumps({k: round(v, 5) if isinstance(v, float) else v for k, v in res.items()}))


if __name__ == "__main__":
    main()
