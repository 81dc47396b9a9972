"""Accuracy of triangulate + the greedy (ch. 4) tracker on the synthetic kitchen world.

Scenes: real CMU motion (``../shared/data/motion``), the kitchen-like room with furniture
occlusion, 2D faults from ``synthetic.render`` (noise, missed joints, left/right flips, false
positive people). Each run goes through the session files exactly as ``reprocess`` does
(``write_session`` -> ``triangulate_session`` -> ``track_session_greedy``) and is scored with
``triangulate.evaluate``: PCP (actor average and frame-weighted), MPJPE, MOTA, IDF1.

Tables: (1) people x cameras at the default faults, (2) degradation as noise, flips,
missed joints and occlusion grow, (3) PCP spread over camera orders (sec. 4.3.6).

    .venv/bin/python bench/bench_triangulate_synthetic.py            # ~3 min on 2 cores
    .venv/bin/python bench/bench_triangulate_synthetic.py --seconds 20 --perms 120
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.synthetic.render import RenderConfig, render  # noqa: E402
from roomcap.synthetic.rigs import kitchen  # noqa: E402
from roomcap.synthetic.world import SceneConfig, make_scene, write_session  # noqa: E402
from roomcap.track.greedy_stage import track_session_greedy  # noqa: E402
from roomcap.track.trackfile import TrackFile  # noqa: E402
from roomcap.triangulate import evaluate as ev  # noqa: E402
from roomcap.triangulate.matching import MatchConfig  # noqa: E402
from roomcap.triangulate.poses3d import Poses3D  # noqa: E402
from roomcap.triangulate.reconstruct import TriangulateConfig  # noqa: E402
from roomcap.triangulate.stage import triangulate_session  # noqa: E402

DEFAULT_FAULTS = dict(noise_px=3.0, missed_joint_rate=0.10, flip_rate=0.02, false_positive_rate=0.05)


def run(
    n_people: int,
    n_cams: int,
    seconds: float,
    seed: int = 1,
    order: list[str] | None = None,
    tri: TriangulateConfig | None = None,
    scene_cache: dict | None = None,
    **faults,
) -> dict:
    f = dict(DEFAULT_FAULTS, **faults)
    key = (n_people, n_cams, seconds, seed)
    if scene_cache is not None and key in scene_cache:
        rig, scene = scene_cache[key]
    else:
        rig, room = kitchen(n_cams)
        scene = make_scene(room, SceneConfig(n_people=n_people, duration_s=seconds, fps=25.0, seed=seed))
        if scene_cache is not None:
            scene_cache[key] = (rig, scene)
    rd = render(scene, rig, RenderConfig(seed=seed, **f))
    with tempfile.TemporaryDirectory() as d:
        write_session(scene, rd, rig, d)
        cfg = tri or TriangulateConfig()
        if order is not None:
            cfg = TriangulateConfig(
                match=MatchConfig(**{**cfg.match.__dict__, "camera_order": tuple(order)}),
                dlt=cfg.dlt,
                min_joints_3d=cfg.min_joints_3d,
                limb_check=cfg.limb_check,
                fix_flips=cfg.fix_flips,
                merge_dist_m=cfg.merge_dist_m,
            )
        t0 = time.perf_counter()
        triangulate_session(d, cfg)
        t_tri = time.perf_counter() - t0
        track_session_greedy(d)
        p = Poses3D.load(Path(d) / "triangulate/poses3d.npz")
        tf = TrackFile.load(Path(d) / "track/tracks.npz")
    gt = scene.gt_xyz_m
    raw, sm = p.xyz_m.astype(np.float64), tf.xyz_m.astype(np.float64)
    pr, ps = ev.pcp(gt, raw), ev.pcp(gt, sm)
    mr, ms = ev.mpjpe(gt, raw), ev.mpjpe(gt, sm)
    mot = ev.mot_metrics(gt, sm, threshold_m=0.3)
    return {
        "people": n_people,
        "cams": n_cams,
        "frames": int(gt.shape[0]),
        "pcp_raw": pr.actor_average,
        "pcp": ps.actor_average,
        "pcp_frame_weighted": ps.frame_weighted,
        "mpjpe_raw_mm": 1e3 * mr["mpjpe_m"],
        "mpjpe_mm": 1e3 * ms["mpjpe_m"],
        "missed": ms["missed"],
        "mota": mot.mota,
        "idf1": mot.idf1,
        "idsw": mot.id_switches,
        "fp": mot.false_positives,
        "fn": mot.misses,
        "tracks": int(tf.n_tracks),
        "tri_ms_per_frame": 1e3 * t_tri / gt.shape[0],
    }


HEAD = (
    f"{'people':>6} {'cams':>4} {'frames':>6} | {'PCP raw':>7} {'PCP':>6} {'PCPfw':>6} | "
    f"{'MPJPE raw':>9} "
    f"{'MPJPE':>6} | {'MOTA':>6} {'IDF1':>6} {'IDsw':>4} {'FP':>4} {'FN':>4} {'K':>3} | {'ms/frame':>8}"
)


def row(r: dict, label: str = "") -> str:
    return (
        f"{r['people']:>6} {r['cams']:>4} {r['frames']:>6} | {r['pcp_raw']:7.4f} {r['pcp']:6.4f} "
        f"{r['pcp_frame_weighted']:6.4f} | {r['mpjpe_raw_mm']:9.1f} {r['mpjpe_mm']:6.1f} | "
        f"{r['mota']:6.4f} "
        f"{r['idf1']:6.4f} {r['idsw']:4d} {r['fp']:4d} {r['fn']:4d} {r['tracks']:3d} | "
        f"{r['tri_ms_per_frame']:8.1f} {label}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--perms", type=int, default=12, help="camera orders tried (sec. 4.3.6)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--theta-sweep", action="store_true", help="also sweep the matching threshold theta")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cache: dict = {}
    out: dict = {"faults": DEFAULT_FAULTS}

    print(
        f"(1) kitchen, CMU motion, faults {DEFAULT_FAULTS}; PCP = actor average; "
        "'raw' = per-frame triangulation, else after the ch. 4 tracker (gap filling + smoothing sigma=2)"
    )
    print(HEAD)
    main_rows = []
    for n_people, n_cams in ((2, 4), (4, 6), (8, 8), (16, 12)):
        r = run(n_people, n_cams, args.seconds, args.seed, scene_cache=cache)
        main_rows.append(r)
        print(row(r), flush=True)
    out["main"] = main_rows

    print("\n(2) degradation, 6 people x 8 cameras (one fault varied, others at the defaults)")
    print(HEAD)
    deg = []
    for label, kw in (
        ("noise 2 px", dict(noise_px=2.0)),
        ("noise 5 px", dict(noise_px=5.0)),
        ("noise 10 px", dict(noise_px=10.0)),
        ("flips 10%", dict(flip_rate=0.10)),
        ("flips 25%", dict(flip_rate=0.25)),
        ("missed 30%", dict(missed_joint_rate=0.30)),
        ("FP people 30%", dict(false_positive_rate=0.30)),
        ("no furniture occl.", dict(occlusion_furniture=False)),
        ("no occlusion at all", dict(occlusion_furniture=False, occlusion_people=False)),
        ("occluded joints guessed 30%", dict(occluded_guess_rate=0.30)),
    ):
        r = run(6, 8, args.seconds, args.seed, scene_cache=cache, **kw)
        r["label"] = label
        deg.append(r)
        print(row(r, label), flush=True)
    out["degradation"] = deg

    print(f"\n(3) camera order (sec. 4.3.6): 4 people x 5 cameras, {args.perms} random orders")
    rng = np.random.default_rng(0)
    names = [f"cam{i:02d}" for i in range(5)]
    pcps, pcps_raw = [], []
    for _ in range(args.perms):
        order = list(rng.permutation(names))
        r = run(4, 5, args.seconds, args.seed, order=order, scene_cache=cache)
        pcps.append(r["pcp"])
        pcps_raw.append(r["pcp_raw"])
    pcps, pcps_raw = np.asarray(pcps), np.asarray(pcps_raw)
    print(
        f"PCP smoothed: mean {pcps.mean():.4f}, min {pcps.min():.4f}, max {pcps.max():.4f}, "
        f"spread {pcps.max() - pcps.min():.4f}"
    )
    print(
        f"PCP raw:      mean {pcps_raw.mean():.4f}, min {pcps_raw.min():.4f}, max {pcps_raw.max():.4f}, "
        f"spread {pcps_raw.max() - pcps_raw.min():.4f}"
    )
    out["camera_order"] = {
        "n": args.perms,
        "pcp_spread": float(pcps.max() - pcps.min()),
        "pcp_raw_spread": float(pcps_raw.max() - pcps_raw.min()),
        "pcp_mean": float(pcps.mean()),
    }
    if args.theta_sweep:
        print("\n(4) matching threshold theta (px), 16 people x 12 cameras")
        print(HEAD)
        out["theta"] = []
        for theta in (10.0, 20.0, 40.0, 80.0, 160.0):
            r = run(
                16,
                12,
                args.seconds,
                args.seed,
                tri=TriangulateConfig(match=MatchConfig(theta_px=theta)),
                scene_cache=cache,
            )
            r["theta_px"] = theta
            out["theta"].append(r)
            print(row(r, f"theta {theta:g}"), flush=True)
    worst = min(main_rows, key=lambda r: r["pcp"])
    out["summary"] = {
        "min_pcp": min(r["pcp"] for r in main_rows),
        "max_mpjpe_mm": max(r["mpjpe_mm"] for r in main_rows),
        "min_mota": min(r["mota"] for r in main_rows),
        "min_idf1": min(r["idf1"] for r in main_rows),
        "worst_case": f"{worst['people']}x{worst['cams']}",
    }
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
