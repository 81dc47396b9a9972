"""OpenSim inverse kinematics on our TRC against Pose2Sim's own TRC of the same trial (BODY_25B setup).

Pose2Sim's single-participant balancing trial (``session-2024/S00_P00_SingleParticipant/
S00_P00_T01_BalancingTrial``, 4 cameras, 100 frames at 60 fps; the videos are the demo's
``Demo_SinglePerson``). Ours: the chain's track file — by default ``reprocess`` on the trial's own
OpenPose BODY_25B JSON (the 2D input Pose2Sim triangulated), or ``--tracks`` a track file made from
the videos (``python -m roomcap.pipeline.demo --recording .../Demo_SinglePerson``). The participant is the
longest track. Both TRCs go through the same scaling + IK with Pose2Sim's model and BODY_25B setups,
restricted to the markers both have (by name), and once more without ``Neck`` (same name, another
point: ours is the mid-shoulder point, BODY_25B's a detected upper-neck keypoint); reported:
OpenSim's per-frame marker error RMS and max (median and mean over frames) for ours, Pose2Sim's
unfiltered and Butterworth-filtered TRC, and the markers the setup names that our track lacks.

    .venv/bin/python bench/bench_track_opensim.py [--shared ../shared] [--tracks T.npz] [--out DIR]
        [--whole-body] [--videos]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.outputs.export import marker_table, write_trc  # noqa: E402
from roomcap.outputs.opensim_ik import find_setup, run_opensim_trc, setup_marker_names  # noqa: E402
from roomcap.pipeline.cli import main as reprocess  # noqa: E402
from roomcap.track.trackfile import TrackFile, read_trc  # noqa: E402

TRIAL = "data/pose2sim/session-2024/S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial"


def summary(r) -> dict:
    return {
        "frames": r.n_frames,
        "markers": len(r.markers),
        "rms_median_mm": round(1000 * float(np.median(r.rms_m)), 1),
        "rms_mean_mm": round(1000 * float(np.mean(r.rms_m)), 1),
        "max_median_mm": round(1000 * float(np.median(r.max_m)), 1),
        "max_mean_mm": round(1000 * float(np.mean(r.max_m)), 1),
        **per_marker(r),
    }


def per_marker(r) -> dict:
    """Diagnostics from the same IK run (not the protocol's statistics): each marker's error median and
    90th percentile over frames, how often it is the frame's largest, and the per-frame max over the
    markers other than that most frequent one."""
    e = 1000 * np.asarray(r.per_marker_m, float)  # (T,M) mm
    ok = np.isfinite(e).all(0)
    names = [m for m, k in zip(r.markers, ok, strict=True) if k]
    e = e[:, ok]
    if not e.size:
        return {}
    top = np.bincount(np.argmax(e, 1), minlength=len(names))
    worst = int(np.argmax(top))
    rest = np.delete(e, worst, axis=1).max(1) if e.shape[1] > 1 else np.full(len(e), np.nan)
    return {
        "per_marker_mm": {
            n: {
                "median": round(float(np.median(e[:, i])), 1),
                "p90": round(float(np.percentile(e[:, i], 90)), 1),
            }
            for i, n in enumerate(names)
        },
        "frames_marker_is_max": {n: int(c) for n, c in zip(names, top, strict=True) if c},
        f"max_median_mm_without_{names[worst]}": round(float(np.median(rest)), 1),
    }


def track_from_videos(shared: Path, out: Path) -> Path:
    """Demo_SinglePerson videos -> BlazePose heavy (33 landmarks kept) -> whole_body triangulate + track."""
    from roomcap.capture.session import SessionLayout
    from roomcap.keypoints.pipeline import KeypointPipelineConfig as KeypointsConfig
    from roomcap.keypoints.video import run_videos

    demo = shared / "data/pose2sim/demo-wheel-0.10.49/Demo_SinglePerson"
    chain = out / "videos"
    assert reprocess([str(demo), "--out", str(chain), "--stages", "calibration"]) == 0
    lay = SessionLayout(chain / demo.name)
    videos = {p.stem: p for p in sorted((demo / "videos").glob("*.mp4"))}
    kp = KeypointsConfig(model_set="blazepose_heavy", skeleton="model", refine_passes=0)
    from roomcap.calibrate.camera import CameraRig

    run_videos(videos, lay.keypoints_dir, kp, rig=CameraRig.load(lay.rig_toml), progress=None)
    (out / "wb.toml").write_text('[triangulate.options]\nskeleton = "whole_body"\n')
    stages = ["--stages", "triangulate,track", "--config", str(out / "wb.toml")]
    assert reprocess([str(demo), "--out", str(chain), *stages]) == 0
    return lay.tracks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    ap.add_argument("--tracks", type=Path, help="our track file (default: reprocess the trial's JSON)")
    ap.add_argument("--label", default="", help="name of our input in the output")
    ap.add_argument(
        "--videos",
        action="store_true",
        help="ours from the demo's videos (Demo_SinglePerson): BlazePose heavy keypoints in their own "
        "33-point layout, triangulated whole_body (heels and foot tips)",
    )
    ap.add_argument(
        "--whole-body",
        action="store_true",
        help="triangulate with skeleton = whole_body (feet, BODY_25B's upper neck and head top)",
    )
    ap.add_argument("--out", type=Path, help="keep the OpenSim outputs here")
    args = ap.parse_args()
    shared = Path(args.shared)
    trial = shared / TRIAL
    setup_dir = shared / "data/opensim-pose2sim"
    try:
        import opensim  # noqa: F401
    except ImportError:
        print("opensim not installed (pip install 'roomcap[opensim]')")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    if not trial.exists() or not setup_dir.exists():
        print(f"Pose2Sim trial or setups not found under {shared}; pass --shared")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_opensim_"))
    t0 = time.perf_counter()
    tracks = args.tracks
    if args.videos:
        tracks = track_from_videos(shared, out)
    if tracks is None:
        stages = "calibration,keypoints,triangulate,track"
        extra = []
        if args.whole_body:
            (out / "wb.toml").parent.mkdir(parents=True, exist_ok=True)
            (out / "wb.toml").write_text('[triangulate.options]\nskeleton = "whole_body"\n')
            extra = ["--config", str(out / "wb.toml")]
        rc = reprocess([str(trial), "--out", str(out / "chain"), "--stages", stages, *extra])
        assert rc == 0, "reprocess failed"
        tracks = out / "chain" / trial.name / "track" / "tracks.npz"
    tf = TrackFile.load(tracks)
    k = int(np.argmax(tf.mask.any(-1).sum(0)))
    tid = int(tf.track_id[k])
    ours = out / "ours.trc"
    mt = write_trc(tf, tid, ours, marker_table(tf, tid))
    setup = find_setup(setup_dir, "Body25b")
    wanted = setup_marker_names(setup)
    p2s_raw = next((trial / "pose-3d").glob("*_0-100.trc"))
    p2s_filt = next((trial / "pose-3d").glob("*_0-100_filt_butterworth.trc"))
    theirs = read_trc(p2s_raw)[0]
    common = [m for m in wanted if m in mt.names and m in theirs]
    # Same name, other definition: our body19 neck is the mid-shoulder point, OpenPose BODY_25B's
    # (Pose2Sim's "Neck") a detected upper-neck keypoint; the second comparison leaves it out (a
    # whole_body track has BODY_25B's upper neck as Neck: no second comparison).
    same_def = [m for m in common if m != "Neck" or "upper_neck" in tf.joint_names]
    res = {}
    for tag, mk in (("", common), ("_no_neck", same_def)) if same_def != common else (("", common),):
        res["ours" + tag] = run_opensim_trc(
            ours, out / f"ik_ours{tag}", "ours", setup_dir, markerset="Body25b", markers=mk
        )
        res["pose2sim" + tag] = run_opensim_trc(
            p2s_raw, out / f"ik_p2s{tag}", "p2s", setup_dir, markerset="Body25b", markers=mk
        )
        res["pose2sim_butterworth" + tag] = run_opensim_trc(
            p2s_filt, out / f"ik_p2sf{tag}", "p2sf", setup_dir, markerset="Body25b", markers=mk
        )
    full = run_opensim_trc(
        ours, out / "ik_ours_all", "ours_all", setup_dir, markerset="Body25b", markers=None, track_id=tid
    )
    report = {
        "input": args.label
        or ("Demo_SinglePerson videos, BlazePose heavy" if args.videos else None)
        or ("trial OpenPose JSON" if args.tracks is None else str(args.tracks)),
        "skeleton": "whole_body" if len(tf.joint_names) > 19 else "body19",
        "track": tid,
        "ours_trc_frames": int(mt.complete.sum()),
        "common_markers": common,
        "setup_markers_track_lacks": full.missing,
        **{k: summary(v) for k, v in res.items()},
        "ours_all_markers": summary(full),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    for name in res:
        s = report[name]
        print(
            f"{name:30s} {s['frames']:4d} frames {s['markers']:2d} markers  RMS median "
            f"{s['rms_median_mm']:6.1f} mm mean {s['rms_mean_mm']:6.1f} | max median "
            f"{s['max_median_mm']:6.1f} mean {s['max_mean_mm']:6.1f}"
        )
    for name in res:
        s = report[name]
        if "frames_marker_is_max" in s:
            worst = max(s["frames_marker_is_max"], key=s["frames_marker_is_max"].get)
            pm = s["per_marker_mm"]
            print(
                f"  {name}: largest marker per frame {s['frames_marker_is_max']}; {worst} median "
                f"{pm[worst]['median']} p90 {pm[worst]['p90']} mm; max per frame without {worst}: median "
                f"{s[f'max_median_mm_without_{worst}']} mm"
            )
    print(f"setup markers our track lacks: {full.missing}")
    print("BENCH " + json.dumps(report))


if __name__ == "__main__":
    main()
