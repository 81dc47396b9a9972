"""Recording N cameras (file replay and synthetic) for S seconds: drops, CPU, timestamp agreement.

    .venv/bin/python bench/bench_capture_record.py                     # 8 x 1080p30 x 60 s, both sources
    .venv/bin/python bench/bench_capture_record.py --seconds 20 --width 1280 --height 720

Baseline measured in the same run: single-thread mp4v/MJPEG encode and decode throughput of one
1080p frame stream, which bounds how many cameras this machine can record at all.
Per source kind it prints frames due vs recorded, drops (source-side sequence gaps + full queues),
process CPU (cores busy, of os.cpu_count()), and the largest disagreement between the recorded
t_ns and the source's own timestamp of that frame (identified by the barcode in the picture).
Ends with one ``BENCH {json}`` line.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.capture.config import parse_config  # noqa: E402
from roomcap.capture.recorder import Recorder  # noqa: E402
from roomcap.capture.sources import SyntheticSource, read_code, read_frames_csv  # noqa: E402


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def make_source_video(path: Path, w: int, h: int, fps: float, n: int) -> Path:
    src = SyntheticSource("gen", w, h, fps, realtime=False, epoch_ns=0, frames=n)
    src.open()
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    while (f := src.read()) is not None:
        wr.write(f.image)
    wr.release()
    return path


def baseline(w: int, h: int, video: Path, n: int = 60) -> dict:
    src = SyntheticSource("b", w, h, 30, realtime=False, epoch_ns=0, frames=n)
    src.open()
    imgs = [src.read().image for _ in range(n)]
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for codec, fourcc, ext in (("mp4v", "mp4v", ".mp4"), ("mjpg", "MJPG", ".avi")):
            api = cv2.CAP_OPENCV_MJPEG if codec == "mjpg" else cv2.CAP_FFMPEG
            wr = cv2.VideoWriter(str(Path(d) / f"x{ext}"), api, cv2.VideoWriter_fourcc(*fourcc), 30, (w, h))
            t = time.perf_counter()
            for im in imgs:
                wr.write(im)
            wr.release()
            out[f"encode_{codec}_fps"] = n / (time.perf_counter() - t)
    cap = cv2.VideoCapture(str(video))
    t = time.perf_counter()
    k = 0
    while cap.read()[0]:
        k += 1
    out["decode_mp4v_fps"] = k / (time.perf_counter() - t)
    return out


def check_timestamps(
    session: Path, cam: str, fps: float, loop_frames: int | None, max_segments: int = 6
) -> dict:
    """Decode a few segments: barcode -> source frame; compare recorded t_ns with the source's timestamp."""
    tab = read_frames_csv(session / "raw" / f"{cam}.frames.csv")
    t0 = tab[0, 1] - int(round(tab[0, 3] * 1e9 / fps))
    # the sequence column is the source's frame counter: the source timestamp is t0 + seq / fps
    err_ns = np.abs(tab[:, 1] - (t0 + np.round(tab[:, 3] * 1e9 / fps).astype(np.int64)))
    segs = sorted((session / "raw" / cam).glob("seg_*.mp4")) + sorted(
        (session / "raw" / cam).glob("seg_*.avi")
    )
    pick = segs[: max_segments // 2] + segs[-(max_segments // 2) :]
    mismatches = checked = 0
    row = 0
    offsets = {}
    for s in segs:
        offsets[s] = row
        row += len(read_frames_csv(s.with_suffix(".frames.csv")))
    for s in pick:
        cap = cv2.VideoCapture(str(s))
        i = offsets[s]
        while True:
            ok, img = cap.read()
            if not ok:
                break
            code = read_code(img)
            seq = int(tab[i, 3])
            want = seq % loop_frames if loop_frames else seq
            mismatches += code != want
            checked += 1
            i += 1
        cap.release()
    return {
        "ts_err_ms_max": float(err_ns.max() / 1e6),
        "frames_checked": checked,
        "barcode_mismatches": mismatches,
    }


def run_one(
    kind: str,
    n: int,
    w: int,
    h: int,
    fps: float,
    seconds: float,
    codec: str,
    video: Path | None,
    loop_frames: int | None,
    tmp: Path,
) -> dict:
    cams = []
    for i in range(n):
        if kind == "file":
            cams.append(
                {"name": f"cam{i:02d}", "source": str(video), "loop": True, "codec": codec, "drop_late": True}
            )
        else:
            cams.append(
                {
                    "name": f"cam{i:02d}",
                    "source": "synthetic:",
                    "resolution": [w, h],
                    "fps": fps,
                    "codec": codec,
                    "quality": 75,
                }
            )
    cfg = parse_config({"cameras": cams, "recorder": {"queue_frames": 30, "min_free_mb": 200}})
    out = tmp / f"session_{kind}"
    load0 = os.getloadavg()[0]
    cpu0, t0 = _cpu_s(), time.monotonic()
    summary = Recorder(cfg, out, duration_s=seconds, handle_signals=False).run()
    wall = time.monotonic() - t0
    cpu = _cpu_s() - cpu0
    per = summary["cameras"]
    rec = [per[c]["frames_written"] for c in per]
    # frames the sources produced while recording: the span of their own frame counters
    tabs = [read_frames_csv(out / "raw" / f"{c}.frames.csv") for c in per]
    due = int(np.mean([t[-1, 3] - t[0, 3] + 1 for t in tabs]))
    dq = [per[c]["dropped_queue"] for c in per]
    ds = [per[c]["dropped_source"] for c in per]
    ts = check_timestamps(out, "cam00", fps, loop_frames)
    timing = summary.get("timing", {})
    size_mb = sum(p.stat().st_size for p in (out / "raw").rglob("*")) / 2**20
    res = {
        "source": kind,
        "cameras": n,
        "resolution": f"{w}x{h}",
        "fps": fps,
        "seconds": seconds,
        "codec": codec,
        "frames_due_per_cam": due,
        "frames_recorded_mean": float(np.mean(rec)),
        "recorded_pct": 100.0 * float(np.mean(rec)) / due,
        "dropped_queue_total": int(sum(dq)),
        "dropped_source_total": int(sum(ds)),
        "cpu_cores_busy": cpu / wall,
        "cpu_pct_of_machine": 100.0 * cpu / wall / os.cpu_count(),
        "wall_s": wall,
        "disk_mb": size_mb,
        "skew_ms_median": timing.get("skew_ms_median"),
        "complete_sets": timing.get("complete_sets"),
        "sets": timing.get("sets"),
        "loadavg_1min_before": load0,
        "loadavg_1min_after": os.getloadavg()[0],
        **ts,
    }
    import shutil

    shutil.rmtree(out)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cams", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--codec", default="mp4v", choices=["mp4v", "mjpg", "xvid"])
    ap.add_argument("--sources", default="file,synthetic")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    w, h = args.width, args.height
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        loop_frames = int(3 * args.fps)
        video = make_source_video(tmp / "source.mp4", w, h, args.fps, loop_frames)
        base = baseline(w, h, video)
        print(
            f"baseline (1 thread, {w}x{h}): encode mp4v {base['encode_mp4v_fps']:.0f} fps, "
            f"MJPEG {base['encode_mjpg_fps']:.0f} fps, decode mp4v {base['decode_mp4v_fps']:.0f} fps; "
            f"{args.cams} cameras need {args.cams * args.fps:.0f} fps"
        )
        results = []
        for kind in args.sources.split(","):
            r = run_one(
                kind,
                args.cams,
                w,
                h,
                args.fps,
                args.seconds,
                args.codec,
                video,
                loop_frames if kind == "file" else None,
                tmp,
            )
            r["load_vs_encode_baseline"] = args.cams * args.fps / base[f"encode_{args.codec}_fps"]
            results.append(r)
            print(
                f"{kind:9s} {r['cameras']} x {r['resolution']}@{r['fps']:g} {r['seconds']:g}s {r['codec']}: "
                f"recorded {r['recorded_pct']:.1f}% of {r['frames_due_per_cam']} frames/cam, dropped "
                f"{r['dropped_source_total']} (source) + {r['dropped_queue_total']} (queue), CPU "
                f"{r['cpu_cores_busy']:.2f} cores ({r['cpu_pct_of_machine']:.0f}% of machine), "
                f"t_ns vs source max {r['ts_err_ms_max']:.3f} ms, barcode mismatches "
                f"{r['barcode_mismatches']}/{r['frames_checked']}, skew median {r['skew_ms_median']} ms, "
                f"disk {r['disk_mb']:.0f} MB; load average {r['loadavg_1min_before']:.1f} -> "
                f"{r['loadavg_1min_after']:.1f} (other processes share the {os.cpu_count()} cores)"
            )
    print("BENCH " + json.dumps({"bench": "capture_record", "baseline": base, "runs": results}))


if __name__ == "__main__":
    main()
