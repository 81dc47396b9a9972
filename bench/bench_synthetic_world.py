"""Synthetic world: time to generate and render the kitchen scene (12 cameras, 8 people, 10 s at 25 fps).

Prints the wall time of each step (scene from CMU mocap with a cold and a warm clip cache,
rendering with every fault on, writing the session folder), the baseline of projecting the same
ground truth into every camera with ``CameraRig.project`` (no occlusion, no faults) measured in
the same run, and a small table over people × cameras. Ends with one line ``BENCH {json}``.

    .venv/bin/python bench/bench_synthetic_world.py [--people 8] [--cams 12] [--seconds 10] [--no-table]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core: BLAS threads only add contention on 2 cores
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.synthetic import bvh, rigs, world  # noqa: E402
from roomcap.synthetic import render as R  # noqa: E402

FAULTS = R.RenderConfig(
    noise_px=3.0,
    missed_joint_rate=0.1,
    flip_rate=0.02,
    false_positive_rate=0.1,
    missed_detection_rate=0.02,
    occluded_guess_rate=0.1,
    time_offset_std_frames=0.5,
    time_drift_std_ppm=100.0,
)


def _best(f, n=3):
    ts, out = [], None
    for _ in range(n):
        t0 = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--people", type=int, default=8)
    ap.add_argument("--cams", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-table", action="store_true")
    a = ap.parse_args()

    rig, room = rigs.kitchen(a.cams)
    cfg = world.SceneConfig(n_people=a.people, duration_s=a.seconds, fps=a.fps, seed=a.seed)
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["ROOMCAP_CACHE"] = tmp  # cold: parse the BVH files
        bvh._load_native.cache_clear()
        t0 = time.perf_counter()
        scene = world.make_scene(room, cfg)
        t_scene_cold = time.perf_counter() - t0
        bvh._load_native.cache_clear()  # warm disk cache, empty memory cache
        t0 = time.perf_counter()
        world.make_scene(room, cfg)
        t_scene_disk = time.perf_counter() - t0
        t_scene_mem, _ = _best(lambda: world.make_scene(room, cfg))

        t_render, r = _best(lambda: R.render(scene, rig, FAULTS))
        t_clean, _ = _best(lambda: R.render(scene, rig, R.RenderConfig()))
        X = scene.gt_xyz_m.reshape(-1, 3)
        t_proj, _ = _best(lambda: rig.project(X))
        t0 = time.perf_counter()
        world.write_session(scene, r, rig, Path(tmp) / "session")
        t_write = time.perf_counter() - t0

    seen = np.isfinite(r.gt_xy_px[..., 0]).sum()
    hidden = 1 - r.visible.sum() / seen
    n_det = sum(int((g >= 0).sum()) for g in r.gt_index)
    n_fp = sum(int((g == -1).sum()) for g in r.gt_index)
    total = t_scene_cold + t_render
    print(
        f"scene {a.cams} cams x {a.people} people x {a.seconds:g} s @ {a.fps:g} fps: clips {scene.clip_names}"
    )
    print(
        f"  scene generation: cold clip cache {t_scene_cold:.3f} s, disk cache {t_scene_disk:.3f} s, "
        f"memory cache {t_scene_mem:.3f} s"
    )
    print(
        f"  render (all faults): {t_render:.3f} s; occlusion only: {t_clean:.3f} s; "
        f"baseline rig.project of the GT: {t_proj:.3f} s (render/project = {t_render / t_proj:.1f}x)"
    )
    print(f"  write_session: {t_write:.3f} s; total scene(cold)+render: {total:.3f} s")
    print(
        f"  joints in an image hidden by occlusion: {hidden:.3f}; GT detections {n_det}, "
        f"false positives {n_fp}"
    )
    table = []
    if not a.no_table:
        print("\n  people x cameras -> render seconds (all faults, 10 s scene)")
        print("  people " + "".join(f"{c:>8d}" for c in (3, 6, 12)))
        for p in (2, 4, 8, 16):
            scfg = world.SceneConfig(n_people=p, duration_s=a.seconds, fps=a.fps, seed=1)
            sc = world.make_scene(room, scfg)
            row = []
            for c in (3, 6, 12):
                rg = rigs.kitchen_rig(c)
                t, _ = _best(lambda sc=sc, rg=rg: R.render(sc, rg, FAULTS), n=1)
                row.append(t)
                table.append({"people": p, "cams": c, "render_s": round(t, 4)})
            print(f"  {p:>6d} " + "".join(f"{t:8.3f}" for t in row))
    print(
        "BENCH "
        + json.dumps(
            {
                "bench": "synthetic_world",
                "cams": a.cams,
                "people": a.people,
                "seconds": a.seconds,
                "fps": a.fps,
                "scene_cold_s": round(t_scene_cold, 4),
                "scene_warm_s": round(t_scene_mem, 4),
                "render_s": round(t_render, 4),
                "render_occlusion_only_s": round(t_clean, 4),
                "baseline_project_s": round(t_proj, 5),
                "render_over_project": round(t_render / t_proj, 1),
                "write_session_s": round(t_write, 4),
                "total_s": round(total, 4),
                "hidden_fraction": round(float(hidden), 4),
                "gt_detections": n_det,
                "false_positives": n_fp,
                "table": table,
            }
        )
    )


if __name__ == "__main__":
    main()
