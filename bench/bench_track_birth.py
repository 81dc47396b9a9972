"""Learned birth generator g (sec. 5.2.3) vs the Gaussian birth (median template + noise), held-out mocap.

Held-out CMU clips (names ending in 1, as in training) at 25 fps, every 5th pose; joints dropped at
random (rates 0.2 / 0.4 / 0.6, hips always kept so the pose has a frame). For the missing joints:
the error of the point fill (network without dropout vs the template), the error of the best of N = 300
samples per joint (what a particle filter can select from) and the coverage (fraction of true
joints within 2 spreads of the sample mean) for the generator's samples (MC dropout + noise) vs the
Gaussian birth (template + ``init_fill_sigma_m`` noise).

    .venv/bin/python bench/bench_track_birth.py [--every 5]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--max-poses", type=int, default=300)
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from roomcap.keypoints.skeletons import CANONICAL
    from roomcap.track.birth import BirthGenerator
    from roomcap.track.normalize import denormalize, hip_frame
    from roomcap.track.particle_config import ParticleConfig
    from roomcap.track.priors import TEMPLATE_BODY19_M
    from roomcap.track.train_motion import load_motion

    clips, names = load_motion(25.0)
    val = np.concatenate([c[:: a.every] for c, n in zip(clips, names, strict=True) if n[-1] == "1"])
    val = val[np.random.default_rng(0).permutation(len(val))[: a.max_poses]].astype(np.float32)
    cfg = ParticleConfig()
    gen = BirthGenerator.load("", sigma_obs_m=cfg.init_sigma_m, sigma_fill_m=cfg.init_sigma_m)
    hips = [CANONICAL.index(n) for n in ("pelvis", "left_hip", "right_hip")]
    rng = np.random.default_rng(1)
    out = {"poses": int(len(val)), "samples": a.samples}
    print(f"{len(val)} held-out poses, N = {a.samples} samples; missing joints only")
    print(
        f"{'drop':>5} | {'fill net':>9} {'fill tmpl':>9} | {'best-of-N net':>13} {'gauss':>7} | "
        f"{'cover net':>9} {'gauss':>7}"
    )
    for rate in (0.2, 0.4, 0.6):
        r = {k: [] for k in ("fill_net", "fill_tmpl", "best_net", "best_gauss", "cov_net", "cov_gauss")}
        for x in val:
            miss = rng.random(19) < rate
            miss[hips] = False
            if not miss.any():
                continue
            cand = x.copy()
            cand[miss] = np.nan
            s = gen.sample(cand, a.samples, rng)  # (N,J,3)
            o, th = hip_frame(cand[None])
            tmpl = denormalize(TEMPLATE_BODY19_M[None], o, th)[0]
            g = tmpl[None] + rng.normal(0, cfg.init_fill_sigma_m, (a.samples, 19, 3)).astype(np.float32)
            t = x[miss]
            r["fill_net"].append(np.linalg.norm(s[0, miss] - t, axis=-1))
            r["fill_tmpl"].append(np.linalg.norm(tmpl[miss] - t, axis=-1))
            for key, smp in (("net", s), ("gauss", g)):
                d = np.linalg.norm(smp[:, miss] - t, axis=-1)  # (N,m)
                r[f"best_{key}"].append(d.min(0))
                mu, sd = smp[:, miss].mean(0), np.sqrt((smp[:, miss].var(0)).sum(-1))
                r[f"cov_{key}"].append(np.linalg.norm(mu - t, axis=-1) < 2 * sd)
        m = {k: float(np.mean(np.concatenate(v))) for k, v in r.items()}
        out[str(rate)] = m
        print(
            f"{rate:5.1f} | {100 * m['fill_net']:7.1f}cm {100 * m['fill_tmpl']:7.1f}cm | "
            f"{100 * m['best_net']:11.1f}cm {100 * m['best_gauss']:5.1f}cm | "
            f"{m['cov_net']:9.2f} {m['cov_gauss']:7.2f}"
        )
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
