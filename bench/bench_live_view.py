"""Live view and streams while recording: the Pose2Sim multi-person demo as 4 file-replay cameras.

Input: ``Demo_MultiPerson`` (4 videos, 1088x1920 portrait, 60 Hz, 100 frames, 2 participants + a
bystander) replayed as cameras at their own pace and looped (``loop: true, realtime: true``), with its
Qualisys calibration. Running the 2D model live is too slow on this shared 2-core machine (about 11 s per
frame set, BENCHMARKS.md), so the ``keypoints`` stage hands the live loop the demo's precomputed 2D
detections of the same frame (OpenPose BODY_25B JSON, ``session-2024/.../S00_P01_T02_Participants1-2``,
frame = the camera's frame number modulo 100); ``triangulate`` and ``track`` are ``capture-run --live``'s
own stages, and the recorder writes every frame as ``capture-run`` does.

Phases, each ``--seconds`` long, in one process:

1. ``baseline``: ``--live`` alone;
2. ``outputs``: ``--live --view --stream lsl,osc`` with a headless Chromium showing the page, an LSL inlet and
   an OSC server on loopback reading everything; a screenshot at 60 % of the phase; the browser killed at
   75 % (the recorder must drop no frame because of it).

Figures:
- latency, frame capture -> page drawn: the page's own readout (median of its last 60 updates, read through
  the DevTools protocol) and, from outside the page, the server's acknowledgements (each drawn update
  acknowledged over the WebSocket, received at ``host_now_ns``; median over the phase);
- CPU: per thread (``time.pthread_getcpuclockid``, from the start of the recording: the server's start-up,
  importing aiohttp, is left out): the live loop (stages + the outputs' feed), the view's
  producer (JPEG encoding) and server threads; the outputs' share = (feed in the live loop + producer +
  server) / (the live loop's own stage work); and the whole process's CPU per second against the baseline
  phase (liblsl's native threads included). Chromium is another process and is not counted;
- frames: every camera's written / grabbed / dropped, per phase; LSL samples and OSC frames received.

    python bench/bench_live_view.py [--seconds 20] [--shared SHARED] [--out DIR]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).parent))

from _live_demo import (  # noqa: E402
    CAMS,
    DEMO,
    SHARED,
    LslReader,
    ThreadCpu,
    loopback_lsl,
    match_lsl_to_frames,
    write_looping_cams,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--shared", default=SHARED)
    ap.add_argument("--out", default=None, help="folder for the screenshot (default: a temporary folder)")
    args = ap.parse_args()
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from roomcap.calibrate.camera import CameraRig
    from roomcap.capture.config import load_config
    from roomcap.capture.live import LiveRunner
    from roomcap.capture.recorder import Recorder
    from roomcap.capture.session import SessionLayout
    from roomcap.keypoints.openpose_json import read_openpose_folder
    from roomcap.pipeline.live import LiveContext, _track, _triangulate
    from roomcap.pipeline.live_outputs import Outputs
    from roomcap.pipeline.liveview.browser import HeadlessBrowser, find_chromium

    demo = Path(args.shared) / DEMO
    trial = (
        Path(args.shared) / "data/pose2sim/session-2024/S00_P01_MultiParticipants/S00_P01_T02_Participants1-2"
    )
    if not demo.exists() or not trial.exists():
        sys.exit(f"bench_live_view: {demo} or {trial} not found; set --shared to the shared data folder")
    if find_chromium() is None:
        sys.exit("bench_live_view: no headless Chromium (apt-get install chromium)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_live_view_"))
    loopback_lsl(tmp)  # LSL on loopback only: liblsl reads LSLAPICFG when it starts
    out_dir = Path(args.out) if args.out else tmp
    out_dir.mkdir(parents=True, exist_ok=True)
    write_looping_cams(demo, tmp)
    rig = CameraRig.load(tmp / "rig.toml")
    cfg = load_config(tmp / "cams.yaml")
    dets = {
        c: read_openpose_folder(trial / "pose" / f"{c}_json", camera=c, skeleton="body25b", fps=60.0)
        for c in CAMS
    }
    n_src = min(len(d.frame_index) for d in dets.values())

    def replayed_keypoints(step):  # the demo's own 2D detections of the frame each camera delivered
        out = {}
        for c in step.cameras:
            f = step.frameset.frames.get(c)
            if f is None:
                continue
            i = int(f.sequence) % n_src
            d = dets[c]
            out[c] = SimpleNamespace(xy_px=d.xy_px[i], score=d.score[i], skeleton=d.skeleton)
        step.outputs["detections"] = out

    def phase(name: str, argv: list[str], browser: bool, seconds: float) -> dict:
        sess = tmp / name
        ctx = LiveContext(cfg, SessionLayout(sess), rig)
        stages = {"keypoints": replayed_keypoints, "triangulate": _triangulate(ctx), "track": _track(ctx)}
        live = LiveRunner(cfg, sess, stages=stages)
        rec = Recorder(cfg, sess, duration_s=seconds, frameset_sink=live.queue, handle_signals=False)
        outputs = Outputs()
        p = argparse.ArgumentParser()
        outputs.add_arguments(p)
        oargs = p.parse_args(argv)
        osc = None
        if oargs.stream and "osc" in ",".join(oargs.stream):
            from pythonosc import dispatcher, osc_server

            osc_frames = [0]

            def on_frame(*_a):
                osc_frames[0] += 1

            d = dispatcher.Dispatcher()
            d.map("/roomcap/frame", on_frame)
            osc = osc_server.BlockingOSCUDPServer(("127.0.0.1", 0), d)
            threading.Thread(target=osc.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True).start()
            oargs.osc_to = f"127.0.0.1:{osc.server_address[1]}"
        close = outputs.open(oargs, live, rec)
        lsl = None
        if oargs.stream and "lsl" in ",".join(oargs.stream):
            lsl = LslReader(f"roomcap-{name}").start()
            if not lsl.wait_open(15.0):
                sys.exit(f"bench_live_view: no LSL stream roomcap-{name} on loopback")
        readouts: list[float] = []
        shot = None
        browser_thread = None
        killed_at = None
        view = outputs.feed.view if outputs.feed is not None else None
        if browser and view is not None:

            def drive():
                nonlocal shot, killed_at
                with HeadlessBrowser(tmp / f"chrome-{name}", size_wh=(1500, 1150)) as b:
                    b.open(view.url)
                    t0 = time.monotonic()
                    while time.monotonic() - t0 < 0.75 * seconds:
                        v = b.evaluate("document.body.dataset.latencyMs")
                        if v:
                            readouts.append(float(v))
                        el = time.monotonic() - t0
                        n_people = b.evaluate("document.body.dataset.people")
                        # the screenshot: when the page shows 3 people (after 30 % of the phase), else at 60 %
                        if shot is None and (el > 0.6 * seconds or (el > 0.3 * seconds and n_people == "3")):
                            shot = b.screenshot(out_dir / "live_view_demo.png")
                            shot_meta["people"] = b.evaluate("document.body.dataset.people")
                            shot_meta["panes_drawn"] = b.evaluate("document.body.dataset.panesDrawn")
                            shot_meta["who"] = b.evaluate("document.getElementById('who').textContent")
                        time.sleep(0.5)
                    killed_at = time.monotonic() - t0
                    b.kill()  # mid-run: the page dies; the recording goes on

            shot_meta: dict = {}
            browser_thread = threading.Thread(target=drive, daemon=True)
            browser_thread.start()
        load0 = os.getloadavg()[0]
        live.start()
        with ThreadCpu() as tc:
            c0, w0 = time.process_time(), time.monotonic()
            summary = rec.run()
            tc.sample()
            live.stop()
            tc.sample()
            c1, w1 = time.process_time(), time.monotonic()
        if browser_thread is not None:
            browser_thread.join(30)
        status = view.status() if view is not None else {}
        close()
        if lsl is not None:
            lsl.stop(drain_s=0.0)
        if osc is not None:
            osc.shutdown()
            osc.server_close()
        s = live.summary()
        cams = {
            c: {
                k: summary["cameras"][c].get(k)
                for k in (
                    "frames_grabbed",
                    "frames_written",
                    "dropped_queue",
                    "dropped_source",
                    "dropped_live",
                )
            }
            for c in CAMS
        }
        feed_s = outputs.feed.cpu_s if outputs.feed is not None else 0.0
        stage_cpu = tc.used("live") + tc.used("live-3d") - feed_s  # the 2D thread, then the 3D and outputs
        out_cpu = feed_s + tc.used("liveview-producer") + tc.used("liveview-server")
        res = {
            "seconds": w1 - w0,
            "process_cpu_per_s": (c1 - c0) / (w1 - w0),
            "outputs_cpu_per_s": out_cpu / (w1 - w0),
            "live_thread_cpu_s": tc.used("live") + tc.used("live-3d"),
            "live_stages_cpu_s": stage_cpu,
            "outputs_feed_cpu_s": feed_s,
            "view_producer_cpu_s": tc.used("liveview-producer"),
            "view_server_cpu_s": tc.used("liveview-server"),
            "outputs_share_of_live_loop": out_cpu / stage_cpu if stage_cpu else None,
            "processed": s["processed"],
            "skipped": s["skipped"],
            "live_latency_ms_median": s["latency_ms_median"],
            "cameras": cams,
            "load_1min": [load0, os.getloadavg()[0]],
        }
        if view is not None:
            lat = view.latency_ms()
            split = np.asarray(view.latency_split_ms()).reshape(-1, 2)
            res.update(
                capture_to_state_ms_median=float(np.median(split[:, 0])) if len(split) else None,
                state_to_page_ms_median=float(np.median(split[:, 1])) if len(split) else None,
                page_latency_ms_readout_median=float(np.median(readouts)) if readouts else None,
                page_latency_ms_acks_median=float(np.median(lat)) if lat else None,
                page_latency_ms_acks_p95=float(np.percentile(lat, 95)) if lat else None,
                acks=len(lat),
                view=status,
                browser_killed_at_s=killed_at,
                screenshot=str(shot) if shot else None,
                screenshot_page=shot_meta if browser else None,
            )
        if oargs.stream:
            res.update(
                lsl_samples=lsl.n if lsl is not None else None,
                osc_frames=osc_frames[0] if osc is not None else None,
            )
            if lsl is not None and lsl.rows:
                res["lsl_vs_live_track"] = _compare_lsl(sess, lsl.rows, lsl.ts, oargs.slots)
        return res

    phase("warmup", [], browser=False, seconds=4.0)  # compiles the tracker's kernels (numba) once
    base = phase("baseline", [], browser=False, seconds=args.seconds)
    full = phase(
        "outputs", ["--view", "--view-port", "0", "--stream", "lsl,osc"], browser=True, seconds=args.seconds
    )
    res = {"baseline": base, "outputs": full}
    res["rerun"] = _rerun_check(tmp / "outputs", tmp / "rig.toml", tmp / "outputs.rrd")
    res["process_cpu_ratio"] = full["process_cpu_per_s"] / base["process_cpu_per_s"]
    # the outputs' own threads against the whole capture-run --live process without them
    res["outputs_share_of_process"] = full["outputs_cpu_per_s"] / base["process_cpu_per_s"]
    drops = {
        ph: sum((c["dropped_queue"] or 0) + (c["dropped_source"] or 0) for c in r["cameras"].values())
        for ph, r in res.items()
        if isinstance(r, dict) and "cameras" in r
    }
    res["recorder_dropped"] = drops
    share = 100 * (full["outputs_share_of_live_loop"] or float("nan"))
    print(
        f"{args.seconds:g} s per phase, 4 file cameras at 60 Hz: page latency (capture -> drawn) readout "
        f"median {full.get('page_latency_ms_readout_median')} ms, acks median "
        f"{full.get('page_latency_ms_acks_median')} ms (p95 {full.get('page_latency_ms_acks_p95')}; "
        f"capture -> state built {full.get('capture_to_state_ms_median')} ms, -> page drawn "
        f"{full.get('state_to_page_ms_median')} ms); "
        f"outputs' CPU share of the live loop's stages {share:.1f} %, of the --live process "
        f"{100 * res['outputs_share_of_process']:.1f} %; process CPU x{res['process_cpu_ratio']:.2f} vs "
        f"--live alone; recorder drops {drops}; LSL samples {full.get('lsl_samples')}, OSC frames "
        f"{full.get('osc_frames')}, "
        f"frame sets processed {full['processed']}; screenshot {full.get('screenshot')} "
        f"{full.get('screenshot_page')}; rerun {res['rerun']}; load {base['load_1min'][0]:.2f}"
    )
    print("BENCH " + json.dumps(res))


def _rerun_check(session: Path, rig_toml: Path, rrd: Path) -> dict:
    """``tracks view`` of the recorded session (its videos, its live track) read back with Rerun's reader:
    entity paths, frames per track and positions against the live track file."""
    import shutil

    try:
        from rerun.chunk import RrdReader
    except ImportError:
        return {"skipped": "rerun-sdk not installed (pip install 'roomcap[rerun]')"}
    from roomcap.capture.session import SessionLayout
    from roomcap.outputs.rerun_recording import write_session_rrd
    from roomcap.track.trackfile import TrackFile

    lay = SessionLayout(session)
    lay.calib_dir.mkdir(exist_ok=True)
    shutil.copy(rig_toml, lay.calib_dir / "rig.toml")
    t0 = time.perf_counter()
    counts = write_session_rrd(session, lay.live_tracks, rrd)
    write_s = time.perf_counter() - t0
    tf = TrackFile.load(lay.live_tracks)
    rows: dict[str, list] = {}
    paths: set[str] = set()
    for c in RrdReader(rrd).stream().to_chunks():
        rb = c.to_record_batch()
        paths.add(str(c.entity_path))
        if "Points3D:positions" in rb.schema.names and "frame" in rb.schema.names:
            fr, pos = rb.column("frame").to_pylist(), rb.column("Points3D:positions").to_pylist()
            rows.setdefault(str(c.entity_path), []).extend((f, p) for f, p in zip(fr, pos, strict=True) if p)
    present = np.isfinite(tf.xyz_m).all(-1).any(-1)
    row_of = {int(f): t for t, f in enumerate(tf.frame_index)}
    equal = True
    for k, tid in enumerate(tf.track_id):
        got = sorted(rows.get(f"/world/tracks/{int(tid)}", []), key=lambda x: x[0])
        equal &= [f for f, _ in got] == [int(f) for f in tf.frame_index[present[:, k]]]
        for f, p in got:
            equal &= bool(np.array_equal(np.asarray(p, np.float32), tf.xyz_m[row_of[f], k], equal_nan=True))
    return {
        **counts,
        "track_frames": tf.n_frames,
        "tracks_equal": bool(equal),
        "camera_entities": sorted(e for e in paths if e.startswith("/world/cameras")),
        "rrd_mb": rrd.stat().st_size / 2**20,
        "write_s": write_s,
    }


def _compare_lsl(session: Path, rows: list, ts: list, slots: int) -> dict:
    """The LSL samples an inlet received against the session's live track file: each sample matched to a
    frame by its timestamp (:func:`_live_demo.match_lsl_to_frames`), positions compared (each slot's track
    id channel names the column); a sample with no frame (a set the track stage skipped: late, out of
    order) must hold nobody."""
    from roomcap.capture.session import SessionLayout
    from roomcap.track.trackfile import TrackFile

    tf = TrackFile.load(SessionLayout(session).live_tracks)
    J = len(tf.joint_names)
    arr = np.asarray(rows, np.float32)
    ids = arr[:, slots * J * 4 :]
    xyz = arr[:, : slots * J * 4].reshape(len(arr), slots, J, 4)[..., :3]
    row, err = match_lsl_to_frames(ts, tf.t_ns)
    equal = True
    for i, t in enumerate(row):
        if t < 0:
            continue
        for s, tid in enumerate(ids[i]):
            if np.isfinite(tid):
                k = int(np.flatnonzero(tf.track_id == int(tid))[0])
                equal &= bool(np.array_equal(xyz[i, s], tf.xyz_m[t, k], equal_nan=True))
    unmatched = row < 0
    return {
        "samples": len(arr),
        "track_file_frames": tf.n_frames,
        "samples_matched": int((~unmatched).sum()),
        "track_frames_without_sample": int(tf.n_frames - len(set(row[~unmatched].tolist()))),
        "unmatched_samples_with_nobody": int((~np.isfinite(ids[unmatched])).all(1).sum()),
        "positions_equal": equal,
        "timestamp_error_ms_max": float(err[~unmatched].max()) if (~unmatched).any() else None,
    }


if __name__ == "__main__":
    main()
