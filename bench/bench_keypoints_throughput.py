"""Keypoints throughput on the Pose2Sim demo (4 portrait 1080x1920 cameras), per model set.

Per stage (decode, detect = letterbox + detector run + decode, crop, pose, decode outputs, write) in ms per
camera-frame, end-to-end frames per second per camera (all cameras processed together, as a session run
does), and the overhead of everything that is not ``session.run`` as a fraction of model time:

- ``overhead_pipeline`` = (time inside the pipeline - session.run time) / session.run time
  (pre-processing, crops, output decoding: what the target "< 15 %" is about);
- ``overhead_end_to_end`` = (wall time - session.run time) / session.run time (adds video decoding, which
  runs in its own threads, and writing);
- ``overhead_pipeline_cpu``: the first, in CPU time of the pipelines' threads (``time.thread_time``) instead
  of wall time: the work outside session.run, without the time a thread waits for a core or the GIL while the
  decoders and the other camera groups run. It counts all of session.run only when onnxruntime runs on the
  calling thread (``--threads 1``, or 2+ camera groups on 2 cores); with more intra-op threads it overstates.

Also measured in the same run: the BlazePose set with its fixed-batch graphs made dynamic so that all crops
of all cameras go in one session.run (what a GPU provider does by default), against the same set with the
original graphs run one crop at a time (the CPU default, see keypoints.runtime.RuntimeConfig).
The machine may be shared: the load average is printed beside the figures.

    .venv/bin/python bench/bench_keypoints_throughput.py [--frames 20] [--sets legacy,balanced,fast] \
        [--demo single|multi] [--threads 1] [--gpu]

``--sets`` takes presets (``keypoints list``) and model sets, ``--extra 'name={"base": "balanced", "pyramid":
"gaussian"}'`` a preset with KeypointPipelineConfig fields overridden; ratios ``x_first`` are against the
first,
measured in the same run. ``--gpu``: every set on the CUDA execution provider (crops batched: the graphs are
made dynamic there) against the CPU; where onnxruntime has no CUDA provider it says so and measures nothing.

``hands_ms``: the hand stage of the ``hands`` presets (forearm crops, hand landmark model, palm detector);
with ``balanced`` in ``--sets`` it is also given as a share of the balanced preset's pipeline time
(``--sets balanced,hands``), with the stage's landmark model and palm detector runs per camera-frame (counts,
which a loaded machine does not change). The hand stage before its back-off, in the same run:
``--extra 'hands_every_frame={"base": "hands", "hand_retry_every": 1}'``.

``--demo multi``: the three people of Demo_MultiPerson (duplicate poses of overlapping people are
re-estimated there, ``KeypointPipeline._resolve_duplicates``; Demo_SinglePerson has none).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import onnxruntime as ort  # noqa: E402

from roomcap.capture.session import videos_in  # noqa: E402
from roomcap.keypoints.pipeline import KeypointPipeline, KeypointPipelineConfig  # noqa: E402
from roomcap.keypoints.presets import preset_config  # noqa: E402
from roomcap.keypoints.registry import presets  # noqa: E402
from roomcap.keypoints.runtime import RuntimeConfig  # noqa: E402
from roomcap.keypoints.video import run_videos  # noqa: E402

SHARED = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
DEMOS = {
    "single": SHARED / "data/pose2sim/demo-wheel-0.10.49/Demo_SinglePerson/videos",
    "multi": SHARED / "data/pose2sim/demo-wheel-0.10.49/Demo_MultiPerson/videos",
}
DEMO = DEMOS["single"]


def measure(name: str, cfg: KeypointPipelineConfig, frames: int, camera_groups: int = 1) -> dict:
    vids = videos_in(DEMO)
    # one camera group: the pipeline made here, to read the hand stage's counts after the run
    pipe = KeypointPipeline(cfg) if camera_groups == 1 else None
    with tempfile.TemporaryDirectory() as tmp:
        rep = run_videos(
            vids, tmp, cfg, max_frames=frames, chunk_frames=25, camera_groups=camera_groups, pipeline=pipe
        )
    n = sum(rep.frames.values())  # camera-frames
    st = rep.stage_s
    ms = lambda k: 1e3 * st.get(k, 0.0) / n  # noqa: E731
    inside = sum(v for k, v in st.items() if k not in ("decode", "write"))
    row = {
        "set": name,
        "camera_frames": n,
        "decode_ms": ms("decode"),
        "detect_ms": ms("detect_pre") + ms("detect") + ms("detect_post"),
        "detect_run_ms": ms("detect"),
        "crop_ms": ms("crop"),
        "pose_ms": ms("pose"),
        "decode_outputs_ms": ms("pose_post") + ms("detect_post"),
        "write_ms": ms("write"),
        # the hand stage (keypoints.hand_model: forearm crops, landmark model, palm detector), inside the rest
        "hands_ms": ms("hand_crop") + ms("hand") + ms("hand_post") + ms("palm"),
        "pipeline_ms": 1e3 * inside / n,
        # CPU time of the pipelines' threads (time.thread_time): less sensitive to a loaded machine
        "pipeline_cpu_ms": 1e3 * rep.pipeline_cpu_s / n,
        "model_ms": 1e3 * rep.model_s / n,
        "fps_per_camera": (n / len(vids)) / rep.wall_s,
        "overhead_pipeline": (inside - rep.model_s) / rep.model_s,
        "overhead_end_to_end": (rep.wall_s - rep.model_s) / rep.model_s,
        "overhead_pipeline_cpu": (rep.pipeline_cpu_s - rep.model_cpu_s) / rep.model_cpu_s,
    }
    hands = pipe.hands if pipe is not None else None
    if hands is not None:  # the hand stage's work, which a loaded machine does not change
        row["hand_crops_per_frame"] = hands.n_crops / n  # landmark model runs
        row["palm_regions_per_frame"] = hands.n_palm_regions / n  # palm detector runs
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=20, help="frames per camera")
    ap.add_argument("--sets", default="legacy,balanced,fast,accurate,feet")
    ap.add_argument(
        "--extra", action="append", default=[], help='name={"base": preset, field: value} (repeatable)'
    )
    ap.add_argument("--gpu", action="store_true", help="CUDA execution provider against the CPU")
    ap.add_argument(
        "--camera-groups",
        type=int,
        nargs="*",
        default=[],
        help="also run with the cameras in N thread groups",
    )
    ap.add_argument("--demo", choices=sorted(DEMOS), default="single", help="which Pose2Sim demo's videos")
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime intra-op threads (0 = its default)")
    args = ap.parse_args()
    global DEMO
    DEMO = DEMOS[args.demo]
    rt = RuntimeConfig(threads=args.threads)
    sets = args.sets.split(",") + args.extra
    label = lambda s: s.partition("=")[0]  # noqa: E731
    known_presets = presets()[1]

    def config(s: str, runtime: RuntimeConfig) -> KeypointPipelineConfig:
        name, _, js = s.partition("=")
        if js:  # name={"base": preset, ...PipelineConfig fields}
            over = json.loads(js)
            return preset_config(over.pop("base", ""), runtime=runtime, **over)
        if s in known_presets:
            return preset_config(s, runtime=runtime)
        return KeypointPipelineConfig(model_set=s, runtime=runtime)

    if args.gpu:
        available = ort.get_available_providers()
        if "CUDAExecutionProvider" not in available:
            print(
                f"GPU benchmark: no CUDA execution provider here (onnxruntime: {available}); nothing measured"
            )
            print("BENCH " + json.dumps({"gpu": False, "providers": available}))
            return
        gpu = RuntimeConfig(providers=("CUDAExecutionProvider", "CPUExecutionProvider"))
        rows = []
        for s in sets:
            rows.append(measure(f"{label(s)} (cpu)", config(s, rt), args.frames))
            rows.append(measure(f"{label(s)} (cuda)", config(s, gpu), args.frames))
    else:
        rows = [measure(label(s), config(s, rt), args.frames) for s in sets]
        for g in args.camera_groups:
            rows += [measure(f"{label(s)} ({g} camera groups)", config(s, rt), args.frames, g) for s in sets]
    for r in rows:
        r["x_first"] = r["fps_per_camera"] / rows[0]["fps_per_camera"]
    if "blazepose" in sets:  # the batching comparison needs the one-crop-per-run BlazePose row
        batched = RuntimeConfig(dynamic_batch=True, threads=args.threads)
        rows.append(
            measure(
                "blazepose-batched",
                KeypointPipelineConfig(model_set="blazepose", runtime=batched),
                args.frames,
            )
        )
    load = os.getloadavg()[0]
    cols = [
        "decode_ms",
        "detect_ms",
        "crop_ms",
        "pose_ms",
        "decode_outputs_ms",
        "hands_ms",
        "write_ms",
        "model_ms",
        "pipeline_ms",
    ]
    print(
        f"{DEMO.parent.name}, 4 cameras 1080x1920, {args.frames} frames each; load average {load:.1f} "
        f"on {os.cpu_count()} cores. ms per camera-frame:"
    )
    print(
        f"{'set':18s} "
        + " ".join(f"{c[:-3]:>9s}" for c in cols)
        + "   fps/cam  x_first  ovh_pipe  ovh_e2e  ovh_cpu"
    )
    for r in rows:
        print(
            f"{r['set']:18s} "
            + " ".join(f"{r[c]:9.1f}" for c in cols)
            + f"   {r['fps_per_camera']:7.2f}  {r['x_first']:7.2f}  {r['overhead_pipeline']:8.1%}"
            + f"  {r['overhead_end_to_end']:7.1%}  {r['overhead_pipeline_cpu']:7.1%}"
        )
    by_set = {r["set"]: r for r in rows}
    if "balanced" in by_set:  # the hand stage's cost against the balanced body preset's, same run
        body = by_set["balanced"]["pipeline_ms"]
        for r in rows:
            if r["hands_ms"] > 0:
                r["hands_vs_balanced"] = r["hands_ms"] / body
                cpu = by_set["balanced"]["pipeline_cpu_ms"]
                r["hands_vs_balanced_cpu"] = (r["pipeline_cpu_ms"] - cpu) / cpu
                counts = ""
                if "hand_crops_per_frame" in r:
                    counts = (
                        f" ({r['hand_crops_per_frame']:.2f} hand crops and "
                        f"{r['palm_regions_per_frame']:.2f} palm regions per camera-frame)"
                    )
                print(
                    f"{r['set']}: hand stage {r['hands_ms']:.1f} ms per camera-frame = "
                    f"{r['hands_vs_balanced']:.0%} of the balanced preset's pipeline ({body:.1f} ms); in CPU "
                    f"time (--threads 1) {r['pipeline_cpu_ms'] - cpu:.1f} ms = "
                    f"{r['hands_vs_balanced_cpu']:.0%} of balanced's {cpu:.1f} ms" + counts
                )
    d = rows[0]
    speedup = float("nan")
    if "blazepose-batched" in by_set:
        speedup = by_set["blazepose-batched"]["fps_per_camera"] / by_set["blazepose"]["fps_per_camera"]
        print(
            f"batching speed-up on this CPU (blazepose batched vs one crop per run, same run): {speedup:.2f}x"
        )
    out = {
        "demo": args.demo,
        "threads": args.threads,
        "frames": args.frames,
        "load_avg": load,
        "rows": rows,
        "first_set": d["set"],
        "first_fps_per_camera": d["fps_per_camera"],
        "first_overhead_pipeline": d["overhead_pipeline"],
        "batching_speedup": speedup,
    }
    print("BENCH " + json.dumps(out, default=float))


if __name__ == "__main__":
    main()
