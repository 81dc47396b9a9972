"""Pipeline throughput: sessions per minute with 1 and 2 workers (local executor) and the scaling efficiency.

Sessions are synthetic detections-only sessions (``pipeline.synth``: 4-camera ring, 1-3 people,
``--seconds`` long at 25 fps) run through triangulate -> track -> forecast -> report into a fresh output
folder per measurement, so every stage really runs; the times include starting the worker processes.
``--real`` adds the two Demo_Batch trials with keypoints on the first ``--max-frames`` video frames.

    .venv/bin/python bench/bench_pipeline_throughput.py [--sessions 8] [--seconds 4] [--real --max-frames 20]

The machine is shared with other work: the load average before and after each measurement is printed.
Ends with one line ``BENCH {json}``.
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

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def measure(paths: list[Path], out: Path, workers: int, stages: tuple[str, ...], max_frames: int | None):
    from pipeline.config import KeypointsConfig, PipelineConfig
    from pipeline.discover import discover
    from pipeline.executors import run_sessions

    cfg = PipelineConfig(stages=stages, keypoints=KeypointsConfig(max_frames=max_frames))
    sources = discover(paths)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    results = run_sessions(sources, out, cfg, force=True, workers=workers)
    dt = time.perf_counter() - t0
    bad = [(r.name, r.message) for r in results if r.status != "ok"]
    if bad:
        raise SystemExit(f"sessions failed: {bad}")
    stage_s = {s: round(sum(r.stage_s.get(s, 0.0) for r in results), 2) for s in stages}
    return {
        "sessions": len(results),
        "wall_s": round(dt, 2),
        "sessions_per_min": round(60 * len(results) / dt, 2),
        "stage_s_sum": stage_s,
        "load_before": round(load0, 1),
        "load_after": round(os.getloadavg()[0], 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=4.0, help="length of each synthetic session")
    ap.add_argument("--real", action="store_true", help="also the Demo_Batch trials (keypoints on videos)")
    ap.add_argument("--max-frames", type=int, default=20)
    a = ap.parse_args()
    from pipeline.synth import make_sessions

    work = Path(tempfile.mkdtemp(prefix="bench_throughput_"))
    try:
        make_sessions(work / "syn", a.sessions, duration_s=a.seconds)
        paths = [work / "syn"]
        stages = ("triangulate", "track", "forecast", "report")
        if a.real:
            shared = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
            paths.append(shared / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_Batch")
            stages = ("keypoints", *stages)
        # warm-up: imports and file caches, not measured
        measure([work / "syn" / "syn_00"], work / "warm", 1, stages[-4:], a.max_frames)
        res = {}
        for w in (1, 2):
            res[w] = measure(paths, work / f"out_{w}", w, stages, a.max_frames if a.real else None)
            print(
                f"{w} worker(s): {res[w]['sessions']} sessions in {res[w]['wall_s']:.1f} s = "
                f"{res[w]['sessions_per_min']:.1f} sessions/min (load average {res[w]['load_before']} -> "
                f"{res[w]['load_after']}); stage seconds summed: {res[w]['stage_s_sum']}"
            )
        speedup = res[2]["sessions_per_min"] / res[1]["sessions_per_min"]
        eff = speedup / 2
        print(
            f"speed-up 2 vs 1 worker: {speedup:.2f}x, scaling efficiency {100 * eff:.0f}% "
            f"({os.cpu_count()} cores)"
        )
        out = {
            "sessions": res[1]["sessions"],
            "session_s": a.seconds,
            "real": a.real,
            "cores": os.cpu_count(),
            "spm_1": res[1]["sessions_per_min"],
            "spm_2": res[2]["sessions_per_min"],
            "speedup_2v1": round(speedup, 2),
            "efficiency_2": round(eff, 2),
            "load_avg": [res[1]["load_before"], res[2]["load_after"]],
        }
        print("BENCH " + json.dumps(out))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
