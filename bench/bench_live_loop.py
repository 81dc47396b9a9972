"""Identities across the loops of a looping live source: ``capture-run --live`` on the Pose2Sim multi-person
demo's 4 videos (1088x1920, 60 Hz, 100 frames = 1.67 s: 2 participants + a bystander) as looping file
cameras (``loop: true, realtime: true``) with its calibration and the real default 2D model, through
``capture-run``'s own code path (``pipeline.live.main``).

Prints the live summary line (frame sets processed, the clock's jumps), the live track's distinct track ids
and the frames each holds, and the jumps recorded in ``track/live.parts/index.json``
(``pipeline.live.load_live_jumps``). The target: 3 identities (the bystander a fourth at most).

    PYTHONPATH=... python bench/bench_live_loop.py [--seconds 60] [--shared DIR]

``--replay-2d N``: instead, N loops of the demo's own 2D detections (OpenPose BODY_25B,
``session-2024/.../S00_P01_T02_Participants1-2``, the same 100 frames) handed to the live ``triangulate`` and
``track`` stages through ``LiveRunner.process`` every ``--stride`` frames (no recording, no real time:
each loop is a frame set whose sources looped, its timestamps going on), so many loops are seen whatever the
machine's load.

The script imports only ``roomcap`` (whichever PYTHONPATH names): run it on two checkouts to compare.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from _live_demo import CAMS, DEMO, SHARED, write_looping_cams  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--shared", default=SHARED)
    ap.add_argument("--replay-2d", type=int, default=0, metavar="N", help="N loops of the demo's 2D instead")
    ap.add_argument("--stride", type=int, default=6, help="with --replay-2d: every this many frames")
    args = ap.parse_args()
    os.environ.setdefault("ROOMCAP_SHARED", args.shared)
    if args.replay_2d:
        return replay_2d(args)
    from roomcap.pipeline.live import main as capture_run

    demo = Path(args.shared) / DEMO
    if not demo.exists():
        sys.exit(f"bench_live_loop: {demo} not found; set --shared")
    tmp = Path(tempfile.mkdtemp(prefix="bench_live_loop_"))
    write_looping_cams(demo, tmp)
    sess = tmp / "S"
    argv = ["--cameras", str(tmp / "cams.yaml"), "--out", str(sess), "--duration", str(args.seconds)]
    out = io.StringIO()
    t0 = time.monotonic()
    with contextlib.redirect_stdout(out):
        rc = capture_run([*argv, "--live", "--quiet", "--no-join"])
    wall = time.monotonic() - t0
    text = out.getvalue()
    line = next((x.strip() for x in text.splitlines() if x.strip().startswith("live:")), "live: (none)")
    load = os.getloadavg()[0]
    print(
        f"exit code {rc}; --duration {args.seconds:g} s, start -> exit {wall:.0f} s; load average {load:.1f}"
    )
    print(line)
    report(sess)
    m = re.search(r"the clock jumped (\d+)", line)
    print(f"summary line states {m.group(1) if m else 0} jumps")
    return 0


def report(sess: Path) -> None:
    """The live track's distinct ids and the jumps it recorded."""
    from roomcap.track.trackfile import TrackFile

    try:
        tf = TrackFile.load(sess / "track" / "live.npz")
    except (OSError, ValueError) as e:
        print(f"no live track: {e}")
        return
    seen = np.isfinite(tf.xyz_m).all(-1).any(-1)  # (T,K)
    people = seen.sum(1)
    print(
        f"live track: {tf.n_frames} frame sets, {len(tf.track_id)} distinct track ids "
        f"{tf.track_id.tolist()}; frames per id {seen.sum(0).tolist()}; people per frame set: median "
        f"{np.median(people):.0f}, max {people.max() if len(people) else 0}"
    )
    try:
        from roomcap.pipeline.live import load_live_jumps
    except ImportError:  # a checkout before the jumps were recorded
        print("jumps recorded: (this checkout does not record them)")
        return
    jumps = load_live_jumps(sess)
    why: dict[str, int] = {}
    for j in jumps:
        why[j["why"]] = why.get(j["why"], 0) + 1
    print(f"jumps recorded in the track file: {len(jumps)} {why}")
    for j in jumps[:3]:
        print(
            "  ",
            {k: j[k] for k in ("frame_set", "row", "why")},
            f"{(j['t_ns_after'] - j['t_ns_before']) / 1e9:+.3f} s",
        )


def replay_2d(args) -> int:
    from types import SimpleNamespace

    from roomcap.calibrate.formats import import_rig
    from roomcap.capture.config import parse_config
    from roomcap.capture.live import LiveRunner
    from roomcap.capture.session import SessionLayout
    from roomcap.capture.sources import Frame, host_now_ns
    from roomcap.capture.sync import FrameSet
    from roomcap.keypoints.openpose_json import read_openpose_folder
    from roomcap.pipeline.live import LiveContext, _track, _triangulate

    shared = Path(args.shared)
    demo = shared / DEMO
    trial = shared / "data/pose2sim/session-2024/S00_P01_MultiParticipants/S00_P01_T02_Participants1-2"
    if not demo.exists() or not trial.exists():
        sys.exit(f"bench_live_loop: {demo} or {trial} not found; set --shared")
    tmp = Path(tempfile.mkdtemp(prefix="bench_live_loop_2d_"))
    rig = import_rig(demo / "calibration" / "Calib.qca.txt")
    cfg = parse_config({"cameras": [{"name": c, "source": "synthetic:", "fps": 60} for c in CAMS]})
    dets = {
        c: read_openpose_folder(trial / "pose" / f"{c}_json", camera=c, skeleton="body25b", fps=60.0)
        for c in CAMS
    }
    n_src = min(len(d.frame_index) for d in dets.values())
    sess = tmp / "S"
    ctx = LiveContext(cfg, SessionLayout(sess), rig)
    by_set: dict[int, dict] = {}

    def keypoints(step):  # the demo's own 2D detections of the frame
        step.outputs["detections"] = by_set[step.frameset.index]

    stages = {"keypoints": keypoints, "triangulate": _triangulate(ctx), "track": _track(ctx)}
    runner = LiveRunner(cfg, sess, stages=stages)
    period = int(round(1e9 / 60.0))
    frames = [(loop, i) for loop in range(args.replay_2d) for i in range(0, n_src, args.stride)]
    t_start = time.monotonic()
    for k, (loop, i) in enumerate(frames):
        t_ns = (loop * n_src + i) * period  # a looping file camera: the time goes on across the wrap
        try:
            fr = {c: Frame(None, t_ns, host_now_ns(), loop * n_src + i, loops=loop) for c in CAMS}
        except TypeError:  # a checkout before Frame.loops
            fr = {c: Frame(None, t_ns, host_now_ns(), loop * n_src + i) for c in CAMS}
        by_set[k] = {
            c: SimpleNamespace(xy_px=dets[c].xy_px[i], score=dets[c].score[i], skeleton=dets[c].skeleton)
            for c in CAMS
        }
        runner.process(FrameSet(k, t_ns, fr), final=k == len(frames) - 1)
    line = "live: " + runner.summary_line()
    print(
        f"{args.replay_2d} loops of the demo's 2D ({n_src} frames at 60 Hz, every {args.stride}): "
        f"{len(frames)} frame sets in {time.monotonic() - t_start:.0f} s"
    )
    print(line)
    report(sess)
    m = re.search(r"the clock jumped (\d+)", line)
    print(f"summary line states {m.group(1) if m else 0} jumps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
