"""Session report: file size and build time for a session with videos (filmstrips embed JPEG frames).

A synthetic session (ring rig of 1280x720 cameras, rendered detections, triangulated and tracked) gets a
video per camera made of real footage (the Pose2Sim demo's frames, cropped to 16:9 and looped; textured
noise when ../shared is absent), then the report is built twice in the same run: without the videos
(baseline: data and overlays only) and with them. Target: a 4-camera, 2-minute session under ~30 MB.

    python bench/bench_report.py --seconds 120 --cams 4 --people 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def footage(n: int, size_wh: tuple[int, int], cam: int) -> list[np.ndarray]:
    """n real frames (the demo video of camera ``cam``, looped) cropped and resized to ``size_wh``."""
    shared = Path(os.environ.get("ROOMCAP_SHARED", Path(__file__).resolve().parents[2] / "shared"))
    demo = shared / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_MultiPerson" / "videos"
    frames = []
    cap = cv2.VideoCapture(str(demo / f"cam0{cam % 4 + 1}.mp4"))
    while len(frames) < n:
        ok, img = cap.read()
        if not ok:
            break
        h, w = img.shape[:2]
        band = img[(h - w * 9 // 16) // 2 :][: w * 9 // 16]  # a 16:9 band of the portrait frame
        frames.append(cv2.resize(band, size_wh, interpolation=cv2.INTER_AREA))
    cap.release()
    if not frames:  # no shared data: moving texture
        rng = np.random.default_rng(cam)
        base = cv2.resize(rng.integers(0, 255, (45, 80, 3), np.uint8), size_wh)
        frames = [np.roll(base, 4 * t, 1) for t in range(50)]
    return frames


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--cams", type=int, default=4)
    ap.add_argument("--people", type=int, default=3)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--keep", type=Path, help="write the session here (kept) instead of a temporary folder")
    a = ap.parse_args(argv)

    from roomcap.pipeline.report import write_report
    from roomcap.synthetic import render as R
    from roomcap.synthetic import rigs, world
    from roomcap.track.greedy_stage import track_session_greedy
    from roomcap.triangulate.stage import triangulate_session

    tmp = Path(tempfile.mkdtemp(prefix="bench_report_")) if a.keep is None else a.keep
    try:
        rig, room = rigs.ring_rig(a.cams, 3.0), rigs.ring_room(3.0)
        scene = world.make_scene(
            room, world.SceneConfig(n_people=a.people, duration_s=a.seconds, fps=a.fps, motion="procedural")
        )
        cfg = R.RenderConfig(noise_px=2.0, missed_joint_rate=0.05, false_positive_rate=0.1)
        lay = world.write_session(scene, R.render(scene, rig, cfg), rig, tmp / "s")
        t = time.perf_counter()
        triangulate_session(lay.root)
        track_session_greedy(lay.root)
        print(f"triangulate + track: {time.perf_counter() - t:.1f} s for {scene.n_frames} frames")
        t = time.perf_counter()
        base = write_report(lay)
        base_s, base_mb = time.perf_counter() - t, base.stat().st_size / 1e6
        print(f"baseline (no videos): {base_mb:.1f} MB in {base_s:.1f} s")
        lay.raw_dir.mkdir(exist_ok=True)
        t = time.perf_counter()
        for c, cam in enumerate(rig.cameras):
            src = footage(200, tuple(cam.size_wh), c)
            wr = cv2.VideoWriter(
                str(lay.raw_dir / f"{cam.name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), a.fps, cam.size_wh
            )
            for i in range(scene.n_frames):
                k = i % (2 * len(src) - 2) if len(src) > 1 else 0  # ping-pong through the footage
                wr.write(src[k if k < len(src) else 2 * len(src) - 2 - k])
            wr.release()
        print(f"videos written in {time.perf_counter() - t:.1f} s")
        t = time.perf_counter()
        path = write_report(lay)
        full_s, full_mb = time.perf_counter() - t, path.stat().st_size / 1e6
        text = path.read_text()
    finally:
        if a.keep is None:
            shutil.rmtree(tmp, ignore_errors=True)
    payload = json.loads(
        text.split('<script id="data" type="application/json">', 1)[1].split("</script>", 1)[0]
    )
    views = payload["views"]
    jpeg_mb = sum(len(u) for c in views["cameras"] for u in c["images"] if u) / 1e6
    print(
        f"with videos: {full_mb:.1f} MB ({jpeg_mb:.1f} MB of base64 JPEG, {len(views['frames'])} frames per "
        f"camera, every {views['sampled_every']:.1f}) in {full_s:.1f} s; ratio to baseline: size "
        f"{full_mb / base_mb:.2f}x, time {full_s / max(base_s, 1e-9):.2f}x"
    )
    res = {
        "seconds": a.seconds,
        "cams": a.cams,
        "frames": int(scene.n_frames),
        "baseline_mb": round(base_mb, 2),
        "baseline_s": round(base_s, 2),
        "report_mb": round(full_mb, 2),
        "report_s": round(full_s, 2),
        "jpeg_base64_mb": round(jpeg_mb, 2),
        "film_frames": len(views["frames"]),
        "size_ratio": round(full_mb / base_mb, 2),
        "time_ratio": round(full_s / max(base_s, 1e-9), 2),
        "under_30mb": full_mb < 30,
    }
    print("BENCH " + json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
