"""Hands on the Pose2Sim single-person demo: how often each hand of the participant is found per view, and in
how many frames at least one hand is in 3D with 15 or more of its 21 joints (the target: 30 % or more).

Runs ``reprocess`` (calibration, keypoints, triangulate) with ``[keypoints] preset`` = the given preset and
``[triangulate.options] skeleton = "whole_body"`` into OUT, then reads the detections and ``poses3d.npz``.
The participant is the largest box per view and the person with the most body joints per 3D frame (the demo's
bystander and the lab's anatomical skeleton model are found too).

    ROOMCAP_SHARED=../shared .venv/bin/python bench/bench_hands_demo.py --out /tmp/hands [--preset hands] \\
        [--skip-run]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from roomcap.keypoints.detections import Detections  # noqa: E402
from roomcap.keypoints.skeletons import HAND_BONES, HAND_LEFT, HAND_RIGHT, get_skeleton  # noqa: E402
from roomcap.triangulate.poses3d import Poses3D  # noqa: E402

SHARED = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
DEMO = SHARED / "data/pose2sim/demo-wheel-0.10.49/Demo_SinglePerson"


def per_view(root: Path) -> dict:
    out = {}
    for p in sorted((root / "keypoints").glob("*.npz")):
        d = Detections.load(p)
        sk = get_skeleton(d.skeleton)
        T = len(d.frame_index)
        b = d.boxes
        area = np.nan_to_num((b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1]) * (b[..., 4] > 0), nan=-1)
        part = np.argmax(area, 1)
        row = {}
        for side, names in (("left", HAND_LEFT), ("right", HAND_RIGHT)):
            full = (d.score[:, :, [sk.index(n) for n in names]] > 0).all(-1)  # (T,P)
            row[side] = float((full[np.arange(T), part] & (area.max(1) > 0)).mean())
        out[d.camera] = row
    return out


def in_3d(root: Path) -> dict:
    P = Poses3D.load(root / "triangulate" / "poses3d.npz")
    names = list(P.joint_names)
    T = len(P.frame_index)
    body = np.isfinite(P.xyz_m[:, :, :19]).all(-1).sum(-1)
    part = np.argmax(body, 1)
    X = P.xyz_m[np.arange(T), part]  # (T,J,3)
    res: dict = {"frames": T}
    seen = np.zeros(T, bool)
    for side, hn in (("left", HAND_LEFT), ("right", HAND_RIGHT)):
        idx = [names.index(n) for n in hn]
        ok = np.isfinite(X[:, idx]).all(-1).sum(-1) >= 15
        seen |= ok
        res[f"{side}_15of21"] = float(ok.mean())
        res[f"{side}_reproj_px_median"] = float(np.nanmedian(P.reproj_err_px[np.arange(T), part][:, idx]))
    res["any_hand_15of21"] = float(seen.mean())
    bones = [(names.index(p), names.index(c)) for p, c in HAND_BONES]
    L = np.array([np.linalg.norm(X[:, c] - X[:, p], axis=-1) for p, c in bones])
    res["bone_median_mm"] = float(np.nanmedian(np.nanmedian(L, 1)) * 1e3)
    res["bone_std_over_time_median_mm"] = float(np.nanmedian(np.nanstd(L, 1)) * 1e3)
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--preset", default="hands")
    ap.add_argument("--skip-run", action="store_true", help="only read an earlier run's outputs")
    args = ap.parse_args()
    if not args.skip_run:
        args.out.mkdir(parents=True, exist_ok=True)
        cfg = args.out / "hands.toml"
        toml = f'[keypoints]\npreset = "{args.preset}"\n[triangulate.options]\nskeleton = "whole_body"\n'
        cfg.write_text(toml)
        exe = Path(sys.executable).with_name("reprocess")
        cmd = [str(exe), str(DEMO), "--out", str(args.out), "--config", str(cfg)]
        subprocess.run([*cmd, "--stages", "calibration,keypoints,triangulate"], check=True)
    root = args.out / DEMO.name
    views, res = per_view(root), in_3d(root)
    print("participant's hand found per view (21 joints):")
    for cam, row in views.items():
        print(f"  {cam}: left {row['left']:.0%}  right {row['right']:.0%}")
    print(
        f"3D: frames with at least one hand (>= 15 of 21 joints) {res['any_hand_15of21']:.0%} of "
        f"{res['frames']} (left {res['left_15of21']:.0%}, right {res['right_15of21']:.0%}); hand joints' "
        f"median reprojection error {res['left_reproj_px_median']:.1f} / "
        f"{res['right_reproj_px_median']:.1f} px; "
        f"finger bones median {res['bone_median_mm']:.0f} mm, median std over time "
        f"{res['bone_std_over_time_median_mm']:.1f} mm"
    )
    print("BENCH " + json.dumps({"preset": args.preset, "views": views, **res}))


if __name__ == "__main__":
    main()
