"""Live 3D stages as a batch of one frame: latency early and late in a long session.

Input: the Pose2Sim multi-person trial (``session-2024/S00_P01_MultiParticipants/
  S00_P01_T02_Participants1-2``:
4 cameras, 2 participants + a bystander, 100 frames at 60 Hz) with its precomputed 2D detections
(OpenPose JSON, BODY_25B) and its Qualisys calibration, looped back and forth in time (frames 0..99,
98..1, 0..99, ...: the motion stays continuous at the seams) for ``--minutes`` (default 5) at 60 Hz
timestamps. Running the keypoint model live for 5 minutes is too slow on this shared 2-core machine, so
the detections are fed to the live 3D stages of ``capture-run --live`` (``pipeline.live``'s
``triangulate`` and ``track`` stage callables, one :class:`roomcap.capture.live.LiveStep` per frame set), not
through the recorder. Each step of both stages is timed as CPU time of this process (``time.process_time``,
robust to the other processes sharing the machine) and wall time (``time.perf_counter``); figures: p50 /
p95 in the first and in the last minute and their ratio (the baseline of this run: the first minute).
Identities: the ids every step returned are compared with those in the live track file, read as any
track file (``TrackFile.load("track/live.npz")``: the parts of ``track/live.parts/``, each checked
against its size and sha256 in the ``parts/1`` index, never rewritten), and counted; the time to
append a part (write, hash, index) is reported too.

    python bench/bench_live_track.py [--minutes 5] [--shared SHARED]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from roomcap.calibrate.camera import CameraRig
    from roomcap.calibrate.formats import import_rig
    from roomcap.capture.config import parse_config
    from roomcap.capture.live import LiveStep
    from roomcap.capture.session import SessionLayout
    from roomcap.capture.sources import Frame
    from roomcap.capture.sync import FrameSet
    from roomcap.keypoints.openpose_json import read_openpose_folder
    from roomcap.pipeline.live import LiveContext, _track, _triangulate, live_dir
    from roomcap.track.trackfile import TrackFile

    base = Path(args.shared) / "data" / "pose2sim" / "session-2024"
    trial = base / "S00_P01_MultiParticipants" / "S00_P01_T02_Participants1-2"
    if not trial.exists():
        sys.exit(f"bench_live_track: {trial} not found; set --shared to the shared data folder")
    fps = 60.0
    names = [f"cam0{i}" for i in range(1, 5)]
    qrig = import_rig(base / "S00_Calibration" / "Calib_qualisys.toml")
    rig = CameraRig(tuple(qrig[f"cam_0{i}"].replace(name=n) for i, n in zip(range(1, 5), names, strict=True)))
    dets = [
        read_openpose_folder(trial / "pose" / f"{n}_json", camera=n, skeleton="body25b", fps=fps)
        for n in names
    ]
    T0 = min(len(d.frame_index) for d in dets)
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": fps} for n in names]})
    n_steps = int(round(args.minutes * 60 * fps))
    cycle = np.r_[np.arange(T0), np.arange(T0 - 2, 0, -1)]  # back and forth
    with tempfile.TemporaryDirectory() as tmp:
        lay = SessionLayout(Path(tmp) / "live")
        ctx = LiveContext(cfg, lay, rig)
        tri, trk = _triangulate(ctx), _track(ctx)
        ms = np.zeros(n_steps)
        wall = np.zeros(n_steps)
        ids_per_step: list[np.ndarray] = []
        load0 = os.getloadavg()[0]
        for t in range(n_steps):
            src = int(cycle[t % len(cycle)])
            t_ns = int(round(t / fps * 1e9))
            dd = {
                n: SimpleNamespace(xy_px=d.xy_px[src], score=d.score[src], skeleton=d.skeleton)
                for n, d in zip(names, dets, strict=True)
            }
            fs = FrameSet(t, t_ns, {n: Frame(None, t_ns, 0, t) for n in names})
            step = LiveStep(fs, tuple(names), {"detections": dd, "final": t == n_steps - 1})
            c0, w0 = time.process_time(), time.perf_counter()
            tri(step)
            trk(step)
            ms[t] = 1e3 * (time.process_time() - c0)
            wall[t] = 1e3 * (time.perf_counter() - w0)
            ids_per_step.append(np.sort(step.outputs["tracks"].track_id))
        t_load = time.perf_counter()
        tf = TrackFile.load(lay.live_tracks)  # the common loader: parts checked against the index
        load_s = time.perf_counter() - t_load
        index = json.loads((live_dir(lay) / "index.json").read_text())
        n_parts = len(index["parts"])
        complete = bool(index["complete"])
    # the file's ids per frame (tracks with an estimate) against what each step returned
    col_ids = tf.track_id
    file_ids = [np.sort(col_ids[np.isfinite(tf.xyz_m[t]).any(-1).any(-1)]) for t in range(tf.n_frames)]
    same_ids = tf.n_frames == n_steps and all(
        np.array_equal(a, b) for a, b in zip(ids_per_step, file_ids, strict=True)
    )
    minute = int(60 * fps)
    wrote = (np.arange(n_steps) + 1) % ctx.chunk_frames == 0  # the steps that appended a part
    wrote[-1] = True
    first, last = ms[:minute], ms[-minute:]
    distinct = sorted({int(i) for ids in ids_per_step for i in ids})
    res = {
        "frames": n_steps,
        "minutes": args.minutes,
        "first_minute_ms": {"p50": float(np.percentile(first, 50)), "p95": float(np.percentile(first, 95))},
        "last_minute_ms": {"p50": float(np.percentile(last, 50)), "p95": float(np.percentile(last, 95))},
        "wall_first_minute_ms": {
            "p50": float(np.percentile(wall[:minute], 50)),
            "p95": float(np.percentile(wall[:minute], 95)),
        },
        "wall_last_minute_ms": {
            "p50": float(np.percentile(wall[-minute:], 50)),
            "p95": float(np.percentile(wall[-minute:], 95)),
        },
        "ratio_last_over_first_p50": float(np.percentile(last, 50) / np.percentile(first, 50)),
        "ratio_last_over_first_p95": float(np.percentile(last, 95) / np.percentile(first, 95)),
        "distinct_track_ids": len(distinct),
        "tracks_at_end": int(len(ids_per_step[-1])),
        "file_ids_equal_step_ids": bool(same_ids),
        "parts": n_parts,
        "index_complete": complete,
        "cpu_ms_mean_steps_appending_a_part": float(ms[wrote].mean()),
        "cpu_ms_mean_other_steps": float(ms[~wrote].mean()),
        "load_live_track_s": load_s,
        "load_1min": [load0, os.getloadavg()[0]],
    }
    print(
        f"{n_steps} frame sets ({args.minutes:g} min at {fps:g} Hz, 4 cameras): 3D stages CPU, first minute "
        f"p50 "
        f"{res['first_minute_ms']['p50']:.2f} / p95 {res['first_minute_ms']['p95']:.2f} ms, last minute p50 "
        f"{res['last_minute_ms']['p50']:.2f} / p95 {res['last_minute_ms']['p95']:.2f} ms "
        f"(x{res['ratio_last_over_first_p50']:.2f}); {len(distinct)} track ids, file = steps: {same_ids}; "
        f"{n_parts} parts (complete: {complete}), steps appending a part "
        f"{res['cpu_ms_mean_steps_appending_a_part']:.2f} ms against "
        f"{res['cpu_ms_mean_other_steps']:.2f} ms, "
        f"TrackFile.load {load_s:.2f} s; load {load0:.2f}"
    )
    print("BENCH " + json.dumps(res))


if __name__ == "__main__":
    main()
