"""`reprocess` over the Pose2Sim Demo_Batch (2 real trials, one shared calibration) plus synthetic sessions.

Shows, in one run (outputs in a temporary folder, never in the shared data):

1. a first run (all stages; keypoints on the real videos) and a second run that does nothing, timed;
2. a run killed with SIGKILL halfway and restarted ends with byte-identical outputs;
3. a deliberately corrupted session fails alone with a clear message (exit status 1);
4. the Ray executor (a local Ray instance) gives the same bytes as the local one (synthetic sessions).

    .venv/bin/python bench/bench_pipeline_reprocess.py [--synthetic 20] [--max-frames N] [--keep DIR]

Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SHARED = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
BATCH = SHARED / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_Batch"


def outputs(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and ".roomcap" not in p.parts and not p.name.startswith("reprocess_summary")
    }


def reprocess(args: list[str], kill_after_s: float | None = None) -> tuple[int, float, str]:
    cmd = [sys.executable, "-m", "roomcap.pipeline.cli", *args]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    if kill_after_s is not None:
        try:
            out, _ = proc.communicate(timeout=kill_after_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the run and its worker processes, as a power cut would
            out, _ = proc.communicate()
            return -9, time.perf_counter() - t0, out
        return proc.returncode, time.perf_counter() - t0, out
    out, _ = proc.communicate()
    return proc.returncode, time.perf_counter() - t0, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synthetic", type=int, default=20)
    ap.add_argument("--max-frames", type=int, help="keypoints: first N frames of each real video")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--kill-after-s", type=float, help="when to SIGKILL the second run (default: half the first)"
    )
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it (default: a temporary one)")
    ap.add_argument("--no-ray", action="store_true")
    a = ap.parse_args()
    if not BATCH.exists():
        print(f"Demo_Batch not found at {BATCH}; set ROOMCAP_SHARED")
        return 2
    work = a.keep or Path(tempfile.mkdtemp(prefix="bench_reprocess_"))
    work.mkdir(parents=True, exist_ok=True)
    from roomcap.pipeline.synth import make_sessions

    syn = work / "synthetic"
    if not syn.exists():
        make_sessions(syn, a.synthetic, duration_s=2.0)
    common = [str(BATCH), str(syn), "--workers", str(a.workers)]
    if a.max_frames:
        common += ["--max-frames", str(a.max_frames)]
    res: dict = {"sessions": a.synthetic + 2, "max_frames": a.max_frames, "workers": a.workers}

    # 1. first run, second run
    ref = work / "out_ref"
    rc, first_s, log1 = reprocess([*common, "--out", str(ref)])
    print(log1)
    rc2, second_s, log2 = reprocess([*common, "--out", str(ref)])
    print(log2.splitlines()[-1])
    summary = json.loads((ref / "reprocess_summary.json").read_text())
    res.update(
        first_rc=rc,
        first_s=round(first_s, 1),
        second_rc=rc2,
        second_s=round(second_s, 2),
        second_ran=sum(len(s["ran"]) for s in summary),
    )
    print(
        f"first run {first_s:.1f} s (exit {rc}); second run {second_s:.2f} s (exit {rc2}), "
        f"stages run the second time: {res['second_ran']}"
    )

    # 2. killed halfway, restarted
    killed = work / "out_killed"
    kill_s = a.kill_after_s or first_s / 2
    rck, ks, _ = reprocess([*common, "--out", str(killed)], kill_after_s=kill_s)
    done_before = len(list(killed.rglob("report.html")))
    rc3, resume_s, log3 = reprocess([*common, "--out", str(killed)])
    got, want = outputs(killed), outputs(ref)
    differ = sorted(k for k in set(got) | set(want) if got.get(k) != want.get(k))
    res.update(
        killed_after_s=round(ks, 1),
        killed_rc=rck,
        reports_before_kill=done_before,
        resume_s=round(resume_s, 1),
        resume_rc=rc3,
        files_compared=len(want),
        files_differing=len(differ),
    )
    print(
        f"killed after {ks:.1f} s ({done_before} of {res['sessions']} reports written), resumed in "
        f"{resume_s:.1f} s: {len(want) - len(differ)}/{len(want)} files byte-identical"
        + (f"; differing: {differ[:8]}" if differ else "")
    )

    # 3. one corrupted session
    bad_in = work / "corrupt_in"
    if bad_in.exists():
        shutil.rmtree(bad_in)
    shutil.copytree(syn, bad_in)
    (bad_in / "syn_03" / "keypoints" / "cam01.npz").write_bytes(b"\x00garbage, not an npz")
    bad_out = work / "out_corrupt"
    shutil.copytree(ref / "synthetic", bad_out / "corrupt_in")  # the others are already done
    rc4, corrupt_s, log4 = reprocess([str(bad_in), "--out", str(bad_out), "--workers", str(a.workers)])
    s4 = json.loads((bad_out / "reprocess_summary.json").read_text())
    failed = [s for s in s4 if s["status"] != "ok"]
    res.update(
        corrupt_rc=rc4,
        corrupt_failed=[s["name"] for s in failed],
        corrupt_message=failed[0]["message"] if failed else "",
    )
    print(
        f"corrupted session: exit {rc4}, failed: {[(s['name'], s['message']) for s in failed]}; "
        f"{len(s4) - len(failed)} others ok"
    )

    # 4. Ray vs local on the synthetic sessions
    if not a.no_ray:
        ray_out = work / "out_ray"
        rc5, ray_s, log5 = reprocess(
            [
                str(syn),
                "--out",
                str(ray_out),
                "--executor",
                "ray",
                "--workers",
                str(a.workers),
                "--stages",
                "triangulate,track,forecast,report",
            ]
        )
        got = outputs(ray_out)
        want = {k: v for k, v in outputs(ref).items() if k.startswith("synthetic/")}
        differ = sorted(k for k in set(got) | set(want) if got.get(k) != want.get(k))
        res.update(ray_rc=rc5, ray_s=round(ray_s, 1), ray_files=len(want), ray_files_differing=len(differ))
        print(
            f"Ray executor: exit {rc5} in {ray_s:.1f} s; {len(want) - len(differ)}/{len(want)} files "
            "identical to the local executor's" + (f"; differing: {differ[:8]}" if differ else "")
        )
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)
    print("BENCH " + json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
