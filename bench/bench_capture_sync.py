"""Offline sync accuracy: known shifts on the Pose2Sim recordings, offsets + drift on the synthetic world.

    .venv/bin/python bench/bench_capture_sync.py [--shared ../shared] [--seeds 3]

Pose2Sim: OpenPose BODY_25B keypoints of the 4 cameras (``session-2024``, the participants of the
demo videos, 100 frames at 60 fps); a camera shifted by k frames = its keypoint track starting k
frames later (k > 0) or earlier (k < 0). The recovered shift is the estimate on the shifted data
minus the estimate on the unshifted data (the baseline: the unshifted recordings' own offsets).
Synthetic: ``synthetic.render_scene`` with per-camera offsets and drifts; error of the offset at
frame 0. Baseline in the same run: the single-channel signal (sum of median person speeds) of
Pose2Sim's approach, against the per-joint multichannel signal used by ``capture-run sync``.
Ends with one ``BENCH {json}`` line.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.capture.offline_sync import estimate_offsets, keypoint_speed, read_openpose_folder  # noqa: E402

CAMS = ("cam01", "cam02", "cam03", "cam04")
TRIALS = (
    "S00_P01_MultiParticipants/S00_P01_T02_Participants1-2",
    "S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial",
)
SHIFTS = ({"cam02": 7, "cam03": -12}, {"cam02": -12, "cam04": 7}, {"cam03": 7, "cam04": -12})


def _shift(sig, k):
    if k > 0:
        return sig[k:]
    return np.concatenate([np.full((-k,) + sig.shape[1:], np.nan), sig]) if k < 0 else sig


def pose2sim(shared: Path, per_joint: bool) -> dict:
    out = {"exact": 0, "total": 0, "max_abs_err_frames": 0.0, "baseline_offsets": {}}
    for trial in TRIALS:
        root = shared / "data" / "pose2sim" / "session-2024" / trial / "pose"
        sig = {
            c: keypoint_speed(read_openpose_folder(root / f"{c}_json")[0], per_joint=per_joint) for c in CAMS
        }
        base = estimate_offsets(sig, 60.0, "cam01", max_lag_s=0.5)["cameras"]
        out["baseline_offsets"][trial.split("/")[-1]] = {
            c: round(b["offset_frames"], 2) for c, b in base.items()
        }
        for shifts in SHIFTS:
            got = estimate_offsets(
                {c: _shift(s, shifts.get(c, 0)) for c, s in sig.items()}, 60.0, "cam01", 0.5
            )
            for c in CAMS:
                rel = got["cameras"][c]["offset_frames"] - base[c]["offset_frames"]
                k = shifts.get(c, 0)
                out["total"] += 1
                out["exact"] += round(rel) == k
                out["max_abs_err_frames"] = max(out["max_abs_err_frames"], abs(rel - k))
    return out


def synthetic_world(seeds: int, per_joint: bool) -> dict:
    from roomcap.synthetic import RenderConfig, SceneConfig, make_scene, render_scene, ring_rig, ring_room

    errs = []
    off = (0.0, 3.4, -7.2, 11.6)
    drift = (0.0, 300.0, -200.0, 150.0)
    for seed in range(seeds):
        scene = make_scene(ring_room(3.0), SceneConfig(n_people=3, duration_s=30, fps=25, seed=seed))
        r = render_scene(
            scene,
            ring_rig(4, 3.0),
            RenderConfig(
                noise_px=2.0, missed_joint_rate=0.1, time_offsets_frames=off, time_drifts_ppm=drift, seed=seed
            ),
        )
        sig = {d.camera: keypoint_speed(d.xy_px, per_joint=per_joint) for d in r.detections}
        res = estimate_offsets(sig, 25.0, r.detections[0].camera, max_lag_s=1.0, drift=True, window_s=8.0)
        for c, d in enumerate(r.detections[1:], 1):
            errs.append(res["cameras"][d.camera]["offset_frames"] - (off[c] - off[0]))
    e = np.abs(errs)
    return {
        "n": len(e),
        "max_abs_err_frames": float(e.max()),
        "mean_abs_err_frames": float(e.mean()),
        "within_one_frame": int((e < 1).sum()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    res = {}
    for name, per_joint in (("per_joint", True), ("single_channel_baseline", False)):
        t = time.perf_counter()
        p = pose2sim(Path(args.shared), per_joint)
        s = synthetic_world(args.seeds, per_joint)
        res[name] = {"pose2sim": p, "synthetic": s, "seconds": time.perf_counter() - t}
        print(
            f"{name:24s} Pose2Sim shifts (+7/-12) recovered exactly: {p['exact']}/{p['total']} "
            f"(max error {p['max_abs_err_frames']:.2f} frames); synthetic offsets within one frame: "
            f"{s['within_one_frame']}/{s['n']} (max {s['max_abs_err_frames']:.2f}, mean "
            f"{s['mean_abs_err_frames']:.2f} frames)"
        )
    print(
        "unshifted Pose2Sim offsets (frames at 60 fps, per-joint):",
        res["per_joint"]["pose2sim"]["baseline_offsets"],
    )
    print("BENCH " + json.dumps({"bench": "capture_sync", **res}))


if __name__ == "__main__":
    main()
