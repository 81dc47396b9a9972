"""Keypoints on the real recordings.

1. Demo_SinglePerson (4 portrait cameras, Qualisys calibration ``Calib.qca.txt``): run a model set,
   triangulate with a plain DLT (per frame: the cross-view choice of detections with the least reprojection
   error), report the median reprojection error per camera. Baseline in the same run: the OpenPose BODY_25B
   detections of the same recording in ``session-2024/.../S00_P00_T01_BalancingTrial`` (the same frames:
   checked by overlaying them on the demo videos) triangulated the same way.
2. Demo_MultiPerson: frames where both participants are found in all four views (two disjoint 4-view
   combinations with median reprojection error under ``--match-px``), and where the bystander (cam01 and
   cam02 only) is a separate third detection.
3. ``opencv/vtest.avi``: people per frame (writes PNGs of a few frames with boxes for a manual count).

    .venv/bin/python bench/bench_keypoints_demo.py [--sets default,movenet] [--step 1] [--out DIR] \
        [--threads 1]

About 2 min per model set on 2 idle cores at --step 1 (100 frames x 4 cameras); --step 4: a quick look.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).parent))

from _kp_demo import read_qca, reprojection_errors  # noqa: E402

from roomcap.keypoints.pipeline import KeypointPipeline, KeypointPipelineConfig  # noqa: E402
from roomcap.keypoints.runtime import RuntimeConfig  # noqa: E402
from roomcap.keypoints.skeletons import convert  # noqa: E402

SHARED = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
P2S = SHARED / "data/pose2sim"
DEMO = P2S / "demo-wheel-0.10.49"
CAMS = ("cam01", "cam02", "cam03", "cam04")


def read_frames(video: Path, step: int, limit: int | None = None) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    out, i = [], 0
    while limit is None or len(out) < limit:
        ok, img = cap.read()
        if not ok:
            break
        if i % step == 0:
            out.append(img)
        i += 1
    return out


def run_set(pipe: KeypointPipeline, frames: dict[str, list[np.ndarray]]):
    """-> per frame, per camera, list of (xy (J,2), score (J,)) and the seconds it took."""
    t0 = time.perf_counter()
    T = min(len(v) for v in frames.values())
    out = []
    for t in range(T):
        res = pipe([frames[c][t] for c in CAMS])
        out.append(
            [[(r.xy_px[k].astype(float), r.score[k].astype(float)) for k in range(len(r.boxes))] for r in res]
        )
    return out, time.perf_counter() - t0


def best_combo(cams, cands, J=19):
    best = (np.inf, None, None)
    for combo in itertools.product(*[range(max(1, len(c))) for c in cands]):
        xy = np.stack([cands[i][k][0] if cands[i] else np.full((J, 2), np.nan) for i, k in enumerate(combo)])
        sc = np.stack([cands[i][k][1] if cands[i] else np.zeros(J) for i, k in enumerate(combo)])
        e, _ = reprojection_errors(cams, xy[:, None], sc[:, None])
        m = np.nanmedian(e) if np.isfinite(e).any() else np.inf
        if m < best[0]:
            best = (m, xy, sc)
    return best


def single_person_errors(cams, per_frame) -> np.ndarray:
    XY, SC = [], []
    for cands in per_frame:
        _, xy, sc = best_combo(cams, cands)
        XY.append(xy)
        SC.append(sc)
    e, _ = reprojection_errors(cams, np.stack(XY, 1), np.stack(SC, 1))
    return e  # (C,T,J)


def openpose_frames(step: int):
    root = P2S / "session-2024/S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial/pose"
    out = []
    for t in range(0, 100, step):
        cands = []
        for c in CAMS:
            js = json.loads((root / f"{c}_json" / f"{c}.{t:04d}.json").read_text())
            cc = []
            for p in js["people"]:
                k = np.array(p["pose_keypoints_2d"]).reshape(-1, 3)
                xy = k[:, :2].copy()
                xy[k[:, 2] <= 0] = np.nan
                cc.append(convert(xy, k[:, 2], "body25b", "body19"))
            cands.append(cc)
        out.append(cands)
    return out


def multi_person(cams, per_frame, match_px: float, min_joints: int = 8) -> dict:
    """Per frame, 4-view combinations of poses (one per view, >= ``min_joints`` joints scored > 0.3) whose
    plain-DLT median reprojection error (all views, all joints) is under ``match_px``.

    ``both_in_4_views``: the greedy reading (best combination first, then the best disjoint from it): a
    wrong combination that happens to score best (one view's pose of the other participant, outvoted by three
    good views) can block the right pair. ``both_in_4_views_pair``: the target's wording, "both participants
    found in all four views": some two disjoint combinations both under ``match_px`` (the pair with the least
    summed error). ``bystander_separate`` / ``_pair``: in those frames, one more pose in cam01 and cam02.
    """
    both = third = both_pair = third_pair = 0
    counts = []
    for cands in per_frame:
        good = [[k for k, (_, s) in enumerate(cc) if (s > 0.3).sum() >= min_joints] for cc in cands]
        counts.append([len(g) for g in good])
        combos = []
        for combo in itertools.product(*good):
            xy = np.stack([cands[i][k][0] for i, k in enumerate(combo)])[:, None]
            sc = np.stack([cands[i][k][1] for i, k in enumerate(combo)])[:, None]
            e, _ = reprojection_errors(cams, xy, sc)
            combos.append((float(np.nanmedian(e)), combo))
        combos.sort(key=lambda x: x[0])
        chosen = []
        for err, combo in combos:
            if err > match_px:
                break
            if all(all(combo[i] != c[i] for i in range(4)) for _, c in chosen):
                chosen.append((err, combo))
        if len(chosen) >= 2:
            both += 1
            used = [{c[i] for _, c in chosen[:2]} for i in range(4)]
            if set(good[0]) - used[0] and set(good[1]) - used[1]:
                third += 1
        ok = [(e, c) for e, c in combos if e <= match_px]
        pairs = [
            (ea + eb, ca, cb)
            for (ea, ca), (eb, cb) in itertools.combinations(ok, 2)
            if all(ca[i] != cb[i] for i in range(4))
        ]
        if pairs:
            both_pair += 1
            _, ca, cb = min(pairs, key=lambda p: p[0])
            if set(good[0]) - {ca[0], cb[0]} and set(good[1]) - {ca[1], cb[1]}:
                third_pair += 1
    T = len(per_frame)
    return {
        "frames": T,
        "both_in_4_views": both / T,
        "bystander_separate": third / T,
        "both_in_4_views_pair": both_pair / T,
        "bystander_separate_pair": third_pair / T,
        "people_per_view_mean": np.mean(counts, 0).round(2).tolist(),
    }


def vtest_counts(pipe: KeypointPipeline, out_dir: Path, show=(0, 200, 400, 600)) -> dict:
    cap = cv2.VideoCapture(str(SHARED / "data/opencv/vtest.avi"))
    counts, i = [], 0
    out_dir.mkdir(parents=True, exist_ok=True)
    while True:
        ok, img = cap.read()
        if not ok:
            break
        if i % 10 == 0 or i in show:
            r = pipe([img])[0]
            counts.append((i, len(r.boxes)))
            if i in show:
                vis = img.copy()
                for k, b in enumerate(r.boxes):
                    cv2.rectangle(vis, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), (0, 255, 0), 1)
                    cv2.putText(vis, str(k), (int(b[0]), int(b[1]) + 10), 0, 0.4, (0, 0, 255), 1)
                cv2.imwrite(str(out_dir / f"vtest_{i:04d}.png"), vis)
        i += 1
    return {"counts": counts, "mean": float(np.mean([c for _, c in counts]))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="default")
    ap.add_argument("--step", type=int, default=1, help="use every n-th frame")
    ap.add_argument("--match-px", type=float, default=30.0)
    ap.add_argument("--out", default="/tmp/kpdemo")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: single,multi,vtest")
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime intra-op threads (0 = its default)")
    args = ap.parse_args()

    def pipeline(s: str) -> KeypointPipeline:
        return KeypointPipeline(
            KeypointPipelineConfig(model_set=s, runtime=RuntimeConfig(threads=args.threads))
        )

    skip = set(args.skip.split(","))
    res: dict = {"step": args.step}
    calib = read_qca(DEMO / "Demo_SinglePerson/calibration/Calib.qca.txt")
    cams = [calib[c] for c in CAMS]
    if "single" not in skip:
        e = single_person_errors(cams, openpose_frames(args.step))
        res["openpose_body25b"] = {
            "median_px": [float(np.nanmedian(x)) for x in e],
            "all": float(np.nanmedian(e)),
        }
        op = res["openpose_body25b"]
        print(
            f"OpenPose BODY_25B (session-2024, same frames): median reprojection px per camera "
            f"{np.round(op['median_px'], 1).tolist()}, all {op['all']:.1f}"
        )
        frames = {c: read_frames(DEMO / "Demo_SinglePerson/videos" / f"{c}.mp4", args.step) for c in CAMS}
        for s in args.sets.split(","):
            pipe = pipeline(s)
            per, sec = run_set(pipe, frames)
            e = single_person_errors(cams, per)
            r = {
                "median_px": [float(np.nanmedian(x)) for x in e],
                "all": float(np.nanmedian(e)),
                "joints_used": int(np.isfinite(e).sum()),
                "s": sec,
            }
            res[f"single_{s}"] = r
            print(
                f"{s:10s} Demo_SinglePerson: median reprojection px per camera "
                f"{np.round(r['median_px'], 1).tolist()}"
                f", all {r['all']:.1f} ({r['joints_used']} joint observations, {sec:.0f} s)"
            )
    if "multi" not in skip:
        frames = {c: read_frames(DEMO / "Demo_MultiPerson/videos" / f"{c}.mp4", args.step) for c in CAMS}
        for s in args.sets.split(","):
            per, _ = run_set(pipeline(s), frames)
            m = multi_person(cams, per, args.match_px)
            res[f"multi_{s}"] = m
            print(
                f"{s:10s} Demo_MultiPerson: both participants in all 4 views {m['both_in_4_views']:.1%} of "
                f"{m['frames']} frames (greedy; any disjoint pair: {m['both_in_4_views_pair']:.1%}); "
                f"bystander separate {m['bystander_separate']:.1%} "
                f"(pair: {m['bystander_separate_pair']:.1%}); "
                f"people/view {m['people_per_view_mean']}"
            )
    if "vtest" not in skip:
        s = args.sets.split(",")[0]
        v = vtest_counts(pipeline(s), Path(args.out))
        res["vtest"] = v
        print(
            f"vtest.avi people per frame ({s}): {v['counts'][:12]} ... mean {v['mean']:.1f}; "
            f"PNGs in {args.out}"
        )
    print("BENCH " + json.dumps(res, default=float))


if __name__ == "__main__":
    main()
