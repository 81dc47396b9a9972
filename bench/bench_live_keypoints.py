"""Where a live frame set's 2D time goes: the live keypoints stage against the batch stage on the same frames.

Input: the Pose2Sim multi-person demo (``Demo_MultiPerson``: 4 videos, 1088x1920 portrait, 60 Hz, 2
participants + a bystander). The frames are decoded once before anything is timed (decoding is the
recorder's cost, measured apart), then:

- ``live``: ``capture-run --live``'s keypoints stage (``pipeline.live._keypoints``, cams.yaml's preset) on
  frame sets taken every ``--step`` frames (the live loop takes the newest set, so consecutive processed
  sets are several frames apart), first set apart from the rest (the model's first runs);
- ``batch``: the batch stage's loop on the same frames (``keypoints.video``: one pipeline per camera group,
  ``camera_groups`` = the cores, each with its share of the onnxruntime threads, crops following the
  previous frame of each camera), every frame of the same span.

Per frame set: the wall time of the stage, its split (detector, pose, pre/post processing: the pipeline's
``stage_s``), the detector's share of images. Ratio live / batch per frame set: the target is 1.3.

    python bench/bench_live_keypoints.py [--frames 60] [--step 6] [--shared DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CAMS = ("cam01", "cam02", "cam03", "cam04")


def _decode(path: Path, n: int) -> list[np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    out = []
    while len(out) < n:
        ok, img = cap.read()
        if not ok:
            break
        out.append(img)
    cap.release()
    return out


def _split(pipes) -> dict[str, float]:
    st: dict[str, float] = {}
    for p in pipes:
        for k, v in p.stage_s.items():
            st[k] = st.get(k, 0.0) + v
        p.stage_s.clear()
    return st


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=60, help="frames per camera decoded (default 60)")
    ap.add_argument("--step", type=int, default=6, help="live: frames between processed sets (default 6)")
    ap.add_argument("--preset", default="", help="cams.yaml's live.preset (default: the default preset)")
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    args = ap.parse_args()
    os.environ.setdefault("ROOMCAP_SHARED", args.shared)

    from roomcap.capture.config import parse_config
    from roomcap.capture.live import LiveStep
    from roomcap.capture.session import SessionLayout
    from roomcap.capture.sources import Frame
    from roomcap.capture.sync import FrameSet
    from roomcap.keypoints.pipeline import KeypointPipeline
    from roomcap.pipeline.config import KeypointsConfig
    from roomcap.pipeline.live import LiveContext, _keypoints

    _ = KeypointPipeline  # the before-variant builds one

    demo = Path(args.shared) / "data/pose2sim/demo-wheel-0.10.49/Demo_MultiPerson/videos"
    if not demo.exists():
        sys.exit(f"bench_live_keypoints: {demo} not found; set --shared")
    frames = {c: _decode(demo / f"{c}.mp4", args.frames) for c in CAMS}
    n = min(len(v) for v in frames.values())
    cfg = parse_config(
        {
            "cameras": [{"name": c, "source": str(demo / f"{c}.mp4")} for c in CAMS],
            "live": {"preset": args.preset},
        }
    )

    def old_stage(ctx):  # the live stage before this bench: one pipeline on every camera, not warmed
        pipe = KeypointPipeline(KeypointsConfig(preset=args.preset, skeleton="body19").detector)

        def stage(step):
            present = [c for c in step.cameras if step.frameset.frames.get(c) is not None]
            res = pipe([step.frameset.frames[c].image for c in present], streams=present)
            step.outputs["detections"] = dict(zip(present, res, strict=True))

        stage.pipes = [pipe]
        return stage

    def run_live(build) -> dict:
        t = time.perf_counter()
        stage = build(LiveContext(cfg, SessionLayout("/nonexistent"), None))
        build_s = time.perf_counter() - t
        pipes = stage.pipes
        wall = []
        for k, i in enumerate(range(0, n, args.step)):
            fs = FrameSet(k, i, {c: Frame(frames[c][i], i, i, i) for c in CAMS})
            t = time.perf_counter()
            stage(LiveStep(fs, CAMS))
            wall.append(time.perf_counter() - t)
        if hasattr(stage, "close"):
            stage.close()
        return {
            "build_s": build_s,
            "wall": np.asarray(wall) * 1e3,
            "split": _split(pipes),
            "det": sum(p.n_detected for p in pipes),
            "trk": sum(p.n_tracked for p in pipes),
        }

    live = {"before": run_live(old_stage), "after": run_live(_keypoints)}

    # ---- batch: keypoints.video's loop (camera groups over the cores, crops following), every frame
    conf = KeypointsConfig(preset=args.preset, skeleton="body19").detector
    groups_n = max(1, min(os.cpu_count() or 1, len(CAMS)))
    threads = max(1, (conf.runtime.threads or os.cpu_count() or 1) // groups_n)
    gconf = replace(conf, runtime=replace(conf.runtime, threads=threads))
    bpipes = [KeypointPipeline(gconf) for _ in range(groups_n)]
    groups = [list(CAMS[g::groups_n]) for g in range(groups_n)]

    def run_group(g: int, i: int) -> None:
        bpipes[g]([frames[c][i] for c in groups[g]], streams=groups[g])

    import cv2

    cv2.setNumThreads(1) if groups_n > 1 else None
    bwall = []
    with ThreadPoolExecutor(groups_n) as pool:
        for i in range(n):
            t = time.perf_counter()
            list(pool.map(run_group, range(groups_n), [i] * groups_n))
            bwall.append(time.perf_counter() - t)
    batch_split = _split(bpipes)

    b = np.asarray(bwall[1:]) * 1e3
    print(f"frames per camera: {n}, live sets: every {args.step}th frame, cores: {os.cpu_count()}")

    def split(d: dict) -> str:
        return "  split (s, summed over the groups): " + ", ".join(
            f"{k} {v:.2f}" for k, v in sorted(d.items())
        )

    for name, r in live.items():
        w = r["wall"]
        med = np.median(w[1:])
        print(
            f"live {name}: built in {r['build_s']:.2f} s, first set {w[0]:.0f} ms, then {med:.0f} ms per set "
            f"(median of {len(w) - 1}; mean {w[1:].mean():.0f}); detector on {r['det']} of "
            f"{r['det'] + r['trk']} images; live / batch {med / np.median(b):.2f}"
        )
        print(split(r["split"]))
    how = f"{groups_n} camera groups x {threads} threads"
    print(f"batch ({how}): {np.median(b):.0f} ms per set (median of {len(b)})")
    print(split(batch_split))
    return 0


if __name__ == "__main__":
    sys.exit(main())
