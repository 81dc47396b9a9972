"""Real data: the particle tracker weighing samples with OpenPose confidence maps + PAFs (eq. 5.8).

Runs the bottom-up model (``openpose_mobilenetv2`` from ../shared/models, ``keep_maps``) on the first
``--frames`` frames of Pose2Sim's ``Demo_MultiPerson`` (4 cameras, 60 fps), then the track stage with
the stored maps (``use_maps``) and with keypoints + scores only, and reports per run: tracks and their
frame counts, the largest frame-to-frame pelvis jump of the long tracks, the median reprojection error of
the output into the detections, and the time per frame.

    .venv/bin/python bench/bench_track_maps.py [--frames 20] [--shared ../shared]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--motion", default="constant_velocity")
    a = ap.parse_args()
    os.environ["ROOMCAP_SHARED"] = a.shared
    from roomcap.calibrate.camera import CameraRig
    from roomcap.calibrate.formats import import_rig
    from roomcap.capture.session import SessionLayout
    from roomcap.core.fileio import save_toml
    from roomcap.keypoints.pipeline import KeypointPipelineConfig
    from roomcap.keypoints.video import run_videos
    from roomcap.track.particle_config import ParticleConfig
    from roomcap.track.stage import track_session_particle
    from roomcap.track.trackfile import TrackFile
    from roomcap.triangulate.multiview import load_detections

    demo = Path(a.shared) / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_MultiPerson"
    videos = {p.stem: p for p in sorted((demo / "videos").glob("cam*.mp4"))}
    rig = import_rig(demo / "calibration" / "Calib.qca.txt")
    names = list(videos)
    rig = CameraRig(tuple(rig[n] if n in rig.names else rig[i].replace(name=n) for i, n in enumerate(names)))
    root = Path(tempfile.mkdtemp(prefix="bench_track_maps_"))
    lay = SessionLayout(root)
    lay.calib_dir.mkdir(parents=True, exist_ok=True)
    rig.save(lay.rig_toml, source="Demo_MultiPerson Calib.qca.txt")
    save_toml(lay.session_toml, {"schema": "session/1", "cameras": names, "fps": 60.0})
    t0 = time.perf_counter()
    run_videos(
        videos,
        lay.keypoints_dir,
        KeypointPipelineConfig(model_set="openpose_mobilenetv2", keep_maps=True),
        rig=rig,
        max_frames=a.frames,
    )
    kp_s = time.perf_counter() - t0
    print(f"keypoints (openpose, maps kept): {a.frames} frames x {len(names)} cameras in {kp_s:.1f} s")
    sub, mv = load_detections(lay, rig)
    out = {"frames": a.frames, "keypoints_s": round(kp_s, 1)}
    for use_maps in (True, False):
        cfg = ParticleConfig(motion=a.motion, use_maps=use_maps, n_samples=300, min_track_s=0.1)
        t0 = time.perf_counter()
        tf = TrackFile.load(track_session_particle(root, cfg))
        dt = (time.perf_counter() - t0) / max(tf.n_frames, 1)
        frames = np.isfinite(tf.xyz_m).all(-1).any(-1).sum(0)
        long = frames >= 0.9 * tf.n_frames
        pel = tf.xyz_m[:, long, 17]
        jump = float(np.nanmax(np.linalg.norm(np.diff(pel, axis=0), axis=-1))) if long.any() else float("nan")
        # reprojection of the output into the detections (nearest detection per camera and joint)
        uv = np.stack([sub[c].project(tf.xyz_m.reshape(-1, 3)) for c in range(len(sub))])
        uv = uv.reshape(len(sub), *tf.xyz_m.shape[:3], 2)  # (C,T,K,J,2)
        det = mv.xy_px  # (C,T,P,J,2) undistorted
        und = np.stack([sub[c].undistort_px(uv[c]) for c in range(len(sub))])
        d = np.linalg.norm(und[:, :, :, None] - det[:, :, None], axis=-1)  # (C,T,K,P,J)
        with np.errstate(all="ignore"):
            e = np.nanmin(np.where(np.isfinite(d), d, np.inf), 3)
        e = e[np.isfinite(e)]
        rep = float(np.median(e)) if e.size else float("nan")
        key = "maps" if use_maps else "keypoints"
        print(
            f"{key:9s}: {tf.n_tracks} tracks, frames per track {sorted(frames.tolist(), reverse=True)}, "
            f"max pelvis jump {100 * jump:.1f} cm, median reprojection {rep:.1f} px, {1e3 * dt:.0f} ms/frame"
        )
        out[key] = {
            "n_tracks": int(tf.n_tracks),
            "frames_per_track": sorted(frames.tolist(), reverse=True),
            "max_pelvis_jump_m": round(jump, 4),
            "median_reproj_px": round(rep, 2),
            "ms_per_frame": round(1e3 * dt, 1),
        }
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
