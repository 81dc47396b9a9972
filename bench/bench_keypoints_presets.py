"""Keypoint presets on both Pose2Sim demos: accuracy, people matched and speed in one table.

For each candidate (today's default chain ``legacy`` is the baseline, measured in the same run):

- ``single_px``: Demo_SinglePerson, 100 frames x 4 portrait 1080x1920 cameras, median reprojection error of
  a plain DLT per frame (``bench_keypoints_demo.single_person_errors``; OpenPose BODY_25B 12.4 px);
- ``both`` / ``bystander``: Demo_MultiPerson, frames of 100 with both participants matched in four views and
  the bystander separate (``bench_keypoints_demo.multi_person``, greedy reading, 30 px);
- ``fps``: frames per second per camera of the 2D pipeline on pre-decoded frames (both demos, all four
  cameras per call, streams = cameras, so tracked crops work as in a session run), and ``x_legacy``, the
  ratio to the baseline's.

    .venv/bin/python bench/bench_keypoints_presets.py [--presets legacy,fast,balanced,accurate,feet] \
        [--extra 'name={"model_set": "...", "detect_every": 8}'] [--frames 100]

Candidates are presets (``keypoints.presets``) or ``name=JSON`` overrides of a preset (``base`` key, default
``legacy``). The machine may be shared: the load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).parent))

from _kp_demo import read_qca  # noqa: E402
from bench_keypoints_demo import CAMS, DEMO, multi_person, read_frames, single_person_errors  # noqa: E402

from roomcap.keypoints.pipeline import KeypointPipeline  # noqa: E402
from roomcap.keypoints.presets import preset_config  # noqa: E402
from roomcap.keypoints.runtime import RuntimeConfig  # noqa: E402


def run(pipe: KeypointPipeline, frames: dict[str, list[np.ndarray]]):
    pipe.reset_streams()
    T = min(len(v) for v in frames.values())
    out = []
    t0 = time.perf_counter()
    for t in range(T):
        res = pipe([frames[c][t] for c in CAMS], streams=CAMS)
        out.append(
            [[(r.xy_px[k].astype(float), r.score[k].astype(float)) for k in range(len(r.boxes))] for r in res]
        )
    return out, time.perf_counter() - t0, T


def candidate(spec: str, threads: int):
    name, _, js = spec.partition("=")
    over = json.loads(js) if js else {}
    base = over.pop("base", name if not js else "legacy")
    # scored in body19 (the metrics' layout); "feet" writes the model's own 33 points in a session
    over.setdefault("skeleton", "body19")
    cfg = preset_config(base, runtime=RuntimeConfig(threads=threads), **over)
    return name, cfg


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--presets", default="legacy,fast,balanced,accurate,feet")
    ap.add_argument("--extra", action="append", default=[], help="name=JSON overrides (repeatable)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--skip", default="", help="single,multi")
    args = ap.parse_args()
    skip = set(args.skip.split(","))
    calib = read_qca(DEMO / "Demo_SinglePerson/calibration/Calib.qca.txt")
    cams = [calib[c] for c in CAMS]
    demo = {
        k: {c: read_frames(DEMO / f"Demo_{k}/videos/{c}.mp4", 1, args.frames) for c in CAMS}
        for k in ("SinglePerson", "MultiPerson")
        if k.lower().removesuffix("person") not in skip
    }
    specs = [p for p in args.presets.split(",") if p] + args.extra
    rows = []
    for spec in specs:
        name, cfg = candidate(spec, args.threads)
        pipe = KeypointPipeline(cfg)
        row: dict = {"name": name, "model_set": cfg.model_set}
        sec = n = 0.0
        if "SinglePerson" in demo:
            per, s, T = run(pipe, demo["SinglePerson"])
            e = single_person_errors(cams, per)
            row["single_px"] = float(np.nanmedian(e))
            row["single_joints"] = int(np.isfinite(e).sum())
            sec, n = sec + s, n + T
        if "MultiPerson" in demo:
            per, s, T = run(pipe, demo["MultiPerson"])
            m = multi_person(cams, per, 30.0)
            row["both"] = round(m["both_in_4_views"] * m["frames"])
            row["bystander"] = round(m["bystander_separate"] * m["frames"])
            sec, n = sec + s, n + T
        row["fps"] = n / sec
        row["detector_share"] = pipe.n_detected / max(pipe.n_detected + pipe.n_tracked, 1)
        row["load"] = os.getloadavg()[0]
        rows.append(row)
        print(json.dumps(row), flush=True)
    base = next((r for r in rows if r["name"] == "legacy"), None)
    if base:
        for r in rows:
            r["x_legacy"] = r["fps"] / base["fps"]
    print(
        "| preset | model set | single px | both | bystander | fps per camera | x legacy | detector frames |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['name']} | {r['model_set']} | {r.get('single_px', float('nan')):.2f} | "
            f"{r.get('both', '')} | {r.get('bystander', '')} | {r['fps']:.2f} | "
            f"{r.get('x_legacy', float('nan')):.2f} | {r['detector_share']:.0%} |"
        )
    print("BENCH " + json.dumps({"rows": rows}))


if __name__ == "__main__":
    main()
