"""Where ``capture-run --live``'s CPU goes, by thread: the recorder's decoding (``grab-*``) and encoding
(``write-*``), the live loop (``live``: the stages; ``live-keypoints*``: the 2D workers; ``live-sync``),
the rest. The Pose2Sim multi-person demo's 4 videos (1088x1920, 60 Hz) as looping file cameras with its
calibration, the real default 2D model, ``capture-run``'s own code path (``pipeline.live.main``).

Prints the live summary line (frame sets processed, stale ones dropped, latency, ms per stage), the frame
sets processed per second of recording, the wall time from the recording's start to the exit, and each
thread group's CPU seconds per second of recording (2.0 = both cores of this machine).

    PYTHONPATH=... python bench/bench_live_profile.py [--seconds 20] [--shared DIR]

The script imports only ``roomcap`` (whichever PYTHONPATH names): run it on two checkouts to compare.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from _live_demo import DEMO, SHARED, ThreadCpu, write_looping_cams  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--shared", default=SHARED)
    args = ap.parse_args()
    os.environ.setdefault("ROOMCAP_SHARED", args.shared)
    import roomcap.capture.recorder as recorder_mod
    from roomcap.pipeline.live import main as capture_run

    demo = Path(args.shared) / DEMO
    if not demo.exists():
        sys.exit(f"bench_live_profile: {demo} not found; set --shared")
    tmp = Path(tempfile.mkdtemp(prefix="bench_live_profile_"))
    write_looping_cams(demo, tmp)
    tc = ThreadCpu(every=0.1)

    started = {}
    make_threads = recorder_mod.Recorder._make_threads

    def timed_make_threads(self, sources):  # the recording's start: the cameras are open
        started["t"] = time.monotonic()
        tc.sample()
        return make_threads(self, sources)

    recorder_mod.Recorder._make_threads = timed_make_threads
    argv = ["--cameras", str(tmp / "cams.yaml"), "--out", str(tmp / "S"), "--duration", str(args.seconds)]
    import contextlib
    import io

    out = io.StringIO()
    with tc, contextlib.redirect_stdout(out):
        rc = capture_run([*argv, "--live", "--quiet", "--no-join"])
    end = time.monotonic()
    text = out.getvalue()
    line = next((x.strip() for x in text.splitlines() if x.strip().startswith("live:")), "live: (none)")
    n = int(re.search(r"live: (\d+)", line).group(1)) if re.search(r"live: (\d+)", line) else 0
    rec_s = args.seconds
    print(f"exit code {rc}; {os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f} at the end")
    print(line)
    print(f"frame sets processed per second of recording: {n / rec_s:.2f}")
    print(f"recording start -> exit: {end - started.get('t', end):.1f} s (--duration {rec_s:g})")
    rows = tc.groups(other="other Python threads")
    for g, v in rows.items():
        print(f"  {g:24s} {v / rec_s:5.2f} CPU s per s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
