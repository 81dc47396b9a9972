"""Pipeline throughput: sessions per minute with 1 and 2 workers (local executor) and the scaling efficiency.

Each measurement is one ``reprocess`` command (a fresh process, all stages, a fresh output folder), so the
figures include starting Python and the workers, as a user sees them. Sessions:

* real (default): the four Pose2Sim demo trials (Demo_Batch's two, Demo_MultiPerson, Demo_SinglePerson;
  4 cameras, 1080x1920), keypoints on the first ``--max-frames`` frames of each video, then
  triangulate -> track -> forecast -> report;
* ``--synthetic N``: N detections-only synthetic sessions (``pipeline.synth``, ``--seconds`` long) instead.

    .venv/bin/python bench/bench_pipeline_throughput.py [--max-frames 20] [--synthetic 8 --seconds 20]

The machine is shared with other work: the load average around each measurement is printed.
Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
DEMOS = SHARED / "data" / "pose2sim" / "demo-wheel-0.10.49"


def measure(paths: list[Path], out: Path, workers: int, extra: list[str]) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "roomcap.pipeline.cli",
        *map(str, paths),
        "--out",
        str(out),
        "--workers",
        str(workers),
        *extra,
    ]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"reprocess failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    results = json.loads((out / "reprocess_summary.json").read_text())
    stages = sorted({s for r in results for s in r["stage_s"]})
    stage_s = {s: round(sum(r["stage_s"].get(s, 0.0) for r in results), 1) for s in stages}
    return {
        "sessions": len(results),
        "wall_s": round(dt, 1),
        "sessions_per_min": round(60 * len(results) / dt, 2),
        "stage_s_sum": stage_s,
        "load_before": round(load0, 1),
        "load_after": round(os.getloadavg()[0], 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--max-frames", type=int, default=20, help="real sessions: frames per video")
    ap.add_argument(
        "--synthetic", type=int, default=0, help="use N synthetic sessions instead of the real ones"
    )
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each synthetic session")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_throughput_"))
    try:
        if a.synthetic:
            from roomcap.pipeline.synth import make_sessions

            make_sessions(work / "syn", a.synthetic, duration_s=a.seconds)
            paths, extra, kind = (
                [work / "syn"],
                ["--stages", "triangulate,track,forecast,report"],
                "synthetic",
            )
        else:
            if not DEMOS.exists():
                print(f"Pose2Sim demos not found at {DEMOS}; set ROOMCAP_SHARED or use --synthetic N")
                return 2
            paths = [DEMOS / "Demo_Batch", DEMOS / "Demo_MultiPerson", DEMOS / "Demo_SinglePerson"]
            extra, kind = ["--max-frames", str(a.max_frames)], "real"
        res = {}
        for w in (1, 2):
            res[w] = measure(paths, work / f"out_{w}", w, extra)
            print(
                f"{w} worker(s): {res[w]['sessions']} {kind} sessions in {res[w]['wall_s']:.1f} s = "
                f"{res[w]['sessions_per_min']:.2f} sessions/min (load average {res[w]['load_before']} -> "
                f"{res[w]['load_after']}); stage seconds summed over sessions: {res[w]['stage_s_sum']}"
            )
        speedup = res[2]["sessions_per_min"] / res[1]["sessions_per_min"]
        eff = speedup / 2
        print(
            f"speed-up 2 vs 1 worker: {speedup:.2f}x, scaling efficiency {100 * eff:.0f}% "
            f"({os.cpu_count()} cores)"
        )
        out = {
            "kind": kind,
            "sessions": res[1]["sessions"],
            "max_frames": None if a.synthetic else a.max_frames,
            "cores": os.cpu_count(),
            "spm_1": res[1]["sessions_per_min"],
            "spm_2": res[2]["sessions_per_min"],
            "wall_s_1": res[1]["wall_s"],
            "wall_s_2": res[2]["wall_s"],
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
