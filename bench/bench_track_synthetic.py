"""Particle tracker (seed ch. 5) vs the chapter-4 greedy tracker on the synthetic world, and the ablation.

The seed's hard setting: the kitchen room with furniture, 3 cameras, people occluding each other
and the furniture, entering and leaving (some leave and come back), real CMU motion, 2D faults
(3 px noise, 10 % missed joints, 2 % left/right flips, 5 % false-positive people). Both trackers
read the same session files (``write_session``): greedy = ``triangulate_session`` +
``track_session_greedy`` (gap filling + smoothing), particle = ``track_session_particle``. Scored
with ``triangulate.evaluate``: MOTA / IDF1 (match within 0.3 m mean joint distance), PCP (actor
average), MPJPE (matched poses, all joints the tracker outputs).

Tables: (1) greedy vs particle over 3 / 4 / 6 cameras; (2) ablation mirroring Table 5.3 on the
3-camera setting (w/o resampling, w/o joint refinement, zero-velocity prior, prior w/o dropout,
plus: constant-velocity prior, the seed's purely random refinement candidates, GRU with 32 / 128 units,
no output smoothing, the learned birth generator g of sec. 5.2.3). ``--ablations WORD ..`` keeps only the
rows whose label contains a word, ``--skip-table1`` skips table (1).

    .venv/bin/python bench/bench_track_synthetic.py                  # ~4 min on 2 busy cores
    .venv/bin/python bench/bench_track_synthetic.py --seconds 20 --seeds 1 2 3
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.synthetic.render import RenderConfig, render  # noqa: E402
from roomcap.synthetic.rigs import kitchen  # noqa: E402
from roomcap.synthetic.world import SceneConfig, make_scene, write_session  # noqa: E402
from roomcap.track.greedy_stage import track_session_greedy  # noqa: E402
from roomcap.track.stage import track_session_particle  # noqa: E402
from roomcap.track.trackfile import TrackFile  # noqa: E402
from roomcap.triangulate import evaluate as ev  # noqa: E402
from roomcap.triangulate.stage import triangulate_session  # noqa: E402

FAULTS = dict(noise_px=3.0, missed_joint_rate=0.10, flip_rate=0.02, false_positive_rate=0.05)
H128 = Path(__file__).resolve().parents[1] / "track" / "checkpoints" / "motion_gru_h128.pt"
H32 = Path(__file__).resolve().parents[1] / "track" / "checkpoints" / "motion_gru_h32.pt"
ABLATIONS = {
    "proposed (GRU 64 units, dropout 0.5)": {},
    "w/o pose resampling": {"resample": False},
    "w/o joint refinement": {"refine": False},
    "zero-velocity prior (w/o pose prediction)": {"motion": "zero_velocity"},
    "prior w/o dropout": {"motion_dropout": 0.0},
    "constant-velocity prior": {"motion": "constant_velocity"},
    "seed's random refinement (M=8, no guided)": {"refine_guided": 0, "refine_candidates": 8},
    "GRU 128 units": {"motion_checkpoint": str(H128)},
    "GRU 32 units": {"motion_checkpoint": str(H32)},
    "no output smoothing": {"smooth_sigma_frames": 0.0},
    "learned birth generator g (sec. 5.2.3)": {"birth": "learned"},
}


def score(gt: np.ndarray, tf: TrackFile) -> dict:
    x = tf.xyz_m.astype(np.float64)
    m = ev.mot_metrics(gt, x, threshold_m=0.3)
    p = ev.pcp(gt, x)
    e = ev.mpjpe(gt, x)
    return {
        "mota": m.mota,
        "idf1": m.idf1,
        "idsw": m.id_switches,
        "fp": m.false_positives,
        "fn": m.misses,
        "pcp": p.actor_average,
        "mpjpe_mm": 1e3 * e["mpjpe_m"],
        "tracks": int(tf.n_tracks),
    }


def session(n_cams: int, n_people: int, seconds: float, seed: int, root: str):
    rig, room = kitchen(n_cams)
    scene = make_scene(
        room,
        SceneConfig(
            n_people=n_people, duration_s=seconds, fps=25.0, seed=seed, enter_leave=True, return_fraction=0.3
        ),
    )
    rd = render(scene, rig, RenderConfig(seed=seed, **FAULTS))
    write_session(scene, rd, rig, root)
    return scene.gt_xyz_m


def joint_errors(gt: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(T,G,J) error of each actor's joints in its closest output pose (mean distance < 0.5 m), or NaN."""
    out = np.full(gt.shape[:3], np.nan)
    for t in range(len(gt)):
        for g in np.flatnonzero(np.isfinite(gt[t]).all(-1).any(-1)):
            e = np.linalg.norm(x[t] - gt[t, g], axis=-1)  # (K,J)
            n = np.isfinite(e).sum(-1)
            if not n.any():
                continue
            d = np.where(n > 0, np.nansum(e, -1) / np.maximum(n, 1), np.inf)
            k = int(np.argmin(d))
            if d[k] < 0.5:
                out[t, g] = e[k]
    return out


def common_mpjpe(gt: np.ndarray, a: TrackFile, b: TrackFile) -> tuple[float, float, float]:
    """MPJPE (mm) of a and b over the joints both output, and b's error on the joints only b outputs."""
    ea, eb = joint_errors(gt, a.xyz_m.astype(np.float64)), joint_errors(gt, b.xyz_m.astype(np.float64))
    both = np.isfinite(ea) & np.isfinite(eb)
    only_b = np.isfinite(eb) & ~np.isfinite(ea)
    return (
        1e3 * float(ea[both].mean()),
        1e3 * float(eb[both].mean()),
        1e3 * float(eb[only_b].mean()) if only_b.any() else float("nan"),
    )


def run_greedy(d: str, gt: np.ndarray) -> dict:
    t0 = time.perf_counter()
    triangulate_session(d)
    track_session_greedy(d)
    r = score(gt, TrackFile.load(Path(d) / "track/tracks.npz"))
    r["ms_per_frame"] = 1e3 * (time.perf_counter() - t0) / len(gt)
    return r


def run_particle(d: str, gt: np.ndarray, **cfg) -> dict:
    t0 = time.perf_counter()
    track_session_particle(d, cfg)
    r = score(gt, TrackFile.load(Path(d) / "track/tracks.npz"))
    r["ms_per_frame"] = 1e3 * (time.perf_counter() - t0) / len(gt)
    return r


HEAD = (
    f"{'':<44} {'MOTA':>6} {'IDF1':>6} {'IDsw':>4} {'FP':>5} {'FN':>5} {'PCP':>6} {'MPJPE':>7} "
    f"{'K':>3} {'ms/fr':>6}"
)


def line(label: str, r: dict) -> str:
    return (
        f"{label:<44} {r['mota']:6.3f} {r['idf1']:6.3f} {r['idsw']:4d} {r['fp']:5d} {r['fn']:5d} "
        f"{r['pcp']:6.3f} {r['mpjpe_mm']:6.1f}mm {r['tracks']:3d} {r['ms_per_frame']:6.1f}"
    )


def mean_rows(rows: list[dict]) -> dict:
    return {
        k: (
            float(np.nanmean([r[k] for r in rows]))
            if isinstance(rows[0][k], float)
            else int(round(np.mean([r[k] for r in rows])))
        )
        for k in rows[0]
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--people", type=int, default=4)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--cams", type=int, nargs="+", default=[3, 4, 6])
    ap.add_argument(
        "--ablations",
        nargs="*",
        default=None,
        help="only the ablation rows whose label contains one of these words (always the first)",
    )
    ap.add_argument("--skip-table1", action="store_true", help="only the ablation table")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    out: dict = {"faults": FAULTS, "people": args.people, "seconds": args.seconds, "seeds": args.seeds}
    print(
        f"kitchen, {args.people} people entering/leaving, {args.seconds:g} s at 25 fps, faults {FAULTS}; "
        f"mean over seeds {args.seeds}"
    )
    print("(1) chapter-4 greedy vs particle filter by number of cameras")
    print(HEAD)
    table1 = {}
    for n_cams in [] if args.skip_table1 else args.cams:
        g_rows, p_rows = [], []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as d:
                gt = session(n_cams, args.people, args.seconds, seed, d)
                g_rows.append(run_greedy(d, gt))
                g_tf = TrackFile.load(Path(d) / "track/tracks.npz")
                p_rows.append(run_particle(d, gt))
                p_tf = TrackFile.load(Path(d) / "track/tracks.npz")
                cg, cp, only = common_mpjpe(gt, g_tf, p_tf)
                g_rows[-1]["mpjpe_common_mm"], p_rows[-1]["mpjpe_common_mm"] = cg, cp
                g_rows[-1]["mpjpe_only_mm"], p_rows[-1]["mpjpe_only_mm"] = float("nan"), only
        g, p = mean_rows(g_rows), mean_rows(p_rows)
        table1[n_cams] = {"greedy": g, "particle": p}
        print(line(f"{n_cams} cams: chapter 4 (greedy + smoothing)", g))
        print(line(f"{n_cams} cams: particle filter (ch. 5)", p), flush=True)
        print(
            f"{'':<44} MPJPE on the joints both output: greedy {g['mpjpe_common_mm']:.1f} mm, particle "
            f"{p['mpjpe_common_mm']:.1f} mm; particle on joints only it outputs (carried through "
            f"occlusion): {p['mpjpe_only_mm']:.1f} mm",
            flush=True,
        )
    out["by_cams"] = table1
    print(f"\n(2) ablation (Table 5.3), {args.cams[0]} cameras")
    print(HEAD)
    table2 = {}
    for i, (label, kw) in enumerate(ABLATIONS.items()):
        if args.ablations is not None and i > 0 and not any(w in label for w in args.ablations):
            continue
        if "motion_checkpoint" in kw and not Path(kw["motion_checkpoint"]).exists():
            continue
        rows = []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as d:
                gt = session(args.cams[0], args.people, args.seconds, seed, d)
                rows.append(run_particle(d, gt, **kw))
        table2[label] = mean_rows(rows)
        print(line(label, table2[label]), flush=True)
    out["ablation"] = table2
    if not table1:
        print("BENCH " + json.dumps(out))
        return
    few = table1[args.cams[0]]
    out["beats_greedy_few_cams"] = bool(
        few["particle"]["mota"] >= few["greedy"]["mota"]
        and few["particle"]["idf1"] >= few["greedy"]["idf1"]
        and few["particle"]["pcp"] >= few["greedy"]["pcp"]
    )
    print(
        f"\nparticle >= greedy on MOTA, IDF1 and PCP with {args.cams[0]} cameras: "
        f"{out['beats_greedy_few_cams']}"
    )
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
