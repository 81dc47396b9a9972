"""Runtime of the particle tracker (seed ch. 5, Table 5.4) per frame for 1-16 people, one CPU core.

Procedural walkers in a 7 m ring of 5 cameras (Shelf has 5), 1 px keypoint noise. Every tracker
runs single-threaded (torch.set_num_threads(1), BLAS threads 1). Frames are timed after all
people are tracked (births excluded), with ``time.process_time`` (CPU time of this process, robust
to other processes sharing the machine) and wall time. A line t = a + b K is fitted over K people:
the seed's claim is linearity (R^2) and its cost per extra person (26 ms with a GPU); the target
is b <= 3 ms with 300 samples. Baselines measured in the same run: the constant-velocity
prior and the ch. 4 per-frame triangulation (quadratic in people).

    .venv/bin/python bench/bench_track_runtime.py                 # ~2 min
    .venv/bin/python bench/bench_track_runtime.py --people 1 2 4 8 16 --frames 40
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from track_helpers import render_kp, ring_P  # noqa: E402

from roomcap.track.particle import ParticleTracker  # noqa: E402
from roomcap.track.particle_config import ParticleConfig  # noqa: E402

H32 = Path(__file__).resolve().parents[1] / "track" / "checkpoints" / "motion_gru_h32.pt"


def people(n: int, T: int, seed: int = 0) -> np.ndarray:
    from roomcap.synthetic.rigs import ring_room
    from roomcap.synthetic.world import SceneConfig, make_scene

    sc = make_scene(
        ring_room(6.5),
        SceneConfig(
            n_people=n, duration_s=T / 25.0, fps=25.0, seed=seed, motion="procedural", min_separation_m=0.8
        ),
    )
    return sc.gt_xyz_m[:T].astype(np.float32)


def time_tracker(P, kp, sc, cfg: ParticleConfig, n_people: int, warm: int) -> dict:
    tr = ParticleTracker(P, np.full(len(P), 1000.0), 25.0, cfg)
    cpu, wall, ks = [], [], []
    for t in range(len(kp)):
        c0, w0 = time.process_time(), time.perf_counter()
        tr.step(kp[t], sc[t], t)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        ks.append(len(tr.tracks))
    ks = np.asarray(ks)
    ok = (np.arange(len(kp)) >= warm) & (ks == n_people)
    if not ok.any():
        ok = np.arange(len(kp)) >= warm
    return {
        "cpu_ms": 1e3 * float(np.median(np.asarray(cpu)[ok])),
        "wall_ms": 1e3 * float(np.median(np.asarray(wall)[ok])),
        "tracks": int(np.median(ks[ok])),
        "frames_timed": int(ok.sum()),
    }


def time_triangulation(P, kp, sc, warm: int) -> float:
    from roomcap.triangulate.reconstruct import FrameReconstructor

    rec = FrameReconstructor(P.astype(np.float64))
    cpu = []
    for t in range(warm, len(kp)):
        c0 = time.process_time()
        rec(kp[t].astype(np.float64), sc[t])
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(cpu))


def fit(k: np.ndarray, t: np.ndarray) -> tuple[float, float, float]:
    b, a = np.polyfit(k, t, 1)
    pred = a + b * k
    r2 = 1 - ((t - pred) ** 2).sum() / max(((t - t.mean()) ** 2).sum(), 1e-12)
    return float(a), float(b), float(r2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--people", type=int, nargs="+", default=[1, 2, 4, 6, 8, 12, 16])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--cams", type=int, default=5)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    P = ring_P(args.cams, radius_m=7.0, height_m=2.6)
    warm = 6
    rows = []
    print(
        f"{args.cams} cameras, {args.samples} samples, median over frames {warm}..{args.frames - 1}; "
        f"CPU ms per frame (process time), wall in ()"
    )
    print(
        f"{'people':>6} | {'GRU 64 prior':>18} | {'const. velocity':>18} | {'GRU 32 prior':>18} | "
        f"{'ch.4 triangulation':>18}"
    )
    for n in args.people:
        X = people(n, args.frames, seed=n)
        kp, sc = render_kp(P, X, noise_px=1.0, seed=n)
        g = time_tracker(P, kp, sc, ParticleConfig(n_samples=args.samples, motion="gru"), n, warm)
        c = time_tracker(
            P, kp, sc, ParticleConfig(n_samples=args.samples, motion="constant_velocity"), n, warm
        )
        g32 = time_tracker(
            P, kp, sc, ParticleConfig(n_samples=args.samples, motion_checkpoint=str(H32)), n, warm
        )
        tri = time_triangulation(P, kp, sc, warm)
        rows.append({"people": n, "gru": g, "cv": c, "gru32": g32, "tri_cpu_ms": tri})
        print(
            f"{n:>6} | {g['cpu_ms']:8.1f} ({g['wall_ms']:6.1f}) K={g['tracks']:<2} | "
            f"{c['cpu_ms']:8.1f} ({c['wall_ms']:6.1f}) K={c['tracks']:<2} | "
            f"{g32['cpu_ms']:8.1f} ({g32['wall_ms']:6.1f}) K={g32['tracks']:<2} | {tri:10.1f}",
            flush=True,
        )
    res = {}
    for name in ("gru", "cv", "gru32"):
        k = np.array([r[name]["tracks"] for r in rows], float)  # the people actually tracked
        t = np.array([r[name]["cpu_ms"] for r in rows])
        a, b, r2 = fit(k, t)
        res[name] = {
            "intercept_ms": a,
            "ms_per_person": b,
            "r2": r2,
            "max_ms_per_person_at_16": float(t[-1] / k[-1]),
        }
        print(
            f"{name}: t = {a:.2f} + {b:.2f} K ms (R^2 = {r2:.4f}); "
            f"at K={int(k[-1])}: {t[-1] / k[-1]:.2f} ms/person"
        )
    k = np.array([r["people"] for r in rows], float)
    tri = np.array([r["tri_cpu_ms"] for r in rows])
    q = np.polyfit(k, tri, 2)
    print(f"ch.4 triangulation per frame: {tri.round(1).tolist()} ms (quadratic term {q[0]:.3f} ms/person^2)")
    ok = res["gru"]["ms_per_person"] <= 3.0 and res["gru"]["r2"] >= 0.98
    print(f"criterion (GRU prior: slope <= 3 ms/person and R^2 >= 0.98): {'met' if ok else 'NOT met'}")
    print(
        "BENCH "
        + json.dumps(
            {"cams": args.cams, "samples": args.samples, "rows": rows, "fit": res, "criterion_met": bool(ok)}
        )
    )


if __name__ == "__main__":
    main()
