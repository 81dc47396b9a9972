"""Live on USB-like cameras: the Pose2Sim multi-person demo's 4 videos as MJPEG cameras at 30 fps, with the
default 2D preset and with ``preset: fast``, against the floor measured in the same run.

The sources: the demo's 4 videos (1088x1920, H.264 at 60 Hz, 100 frames) transcoded with PyAV to MJPEG
(every second frame, so 30 fps and the same motion; quality ``q:v 4``, about 62 kB a frame) in AVI files,
replayed as looping file cameras paced at their own 30 fps (``realtime: true``). Like a USB camera that
streams MJPEG, each frame arrives as one whole JPEG at the camera's rate, intra-coded, and is handed on as
that JPEG (``Frame.jpeg``): the recorder writes it as it came (stream copy) and only the frames the live loop
takes are decoded, at the size the 2D needs. What differs from a USB camera: the timestamps are the file's
(evenly spaced; a USB camera's are the host's at grab) and there is no driver ring buffer that drops frames
when the reader is late (the file camera is never late: it reads packets, not images).

Per preset, one phase of ``--seconds`` in this process, built as ``capture-run --live --view`` builds it
(recorder, LiveRunner with the stages built on the live thread, the live page with a headless Chromium
drawing it when one is installed):
- frame sets processed per second of recording, the share of them complete;
- capture -> 3D: host arrival of a set's newest frame -> the track stage done (median, p95);
- capture -> page drawn: the page's acknowledgements of drawn states, at the server (median);
- where the live loop's time goes: ms per set per stage, decoding the taken frames, each thread group's CPU,
  the other threads by name; the headless Chromium's CPU (all its processes, by process type) and the page's
  main-thread time by kind (DevTools ``Performance.getMetrics``: script, layout, style, the rest).

The floor, measured in the same run before the phases: decoding the JPEGs (full size and at the factor the
live loop uses; ms per camera-frame, one thread) and the 2D alone on the same reduced frames (the live
keypoints stage on 24 frame sets of the 4 cameras, ms per set), giving the most frame sets a second the 2D
allows on this machine now. Then ``python -m roomcap.pipeline.live ... --duration 3`` as a command, its wall
time from launch to exit.

And the 2D on the same JPEG sets decoded at 1/2 and 1/4 against full size (keypoints px apart).

    PYTHONPATH=... python bench/bench_live_usb.py [--seconds 20] [--shared DIR] [--no-browser] [--no-accuracy]

Ends with one ``BENCH {json}`` line.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from fractions import Fraction  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))

from _live_demo import CAMS, DEMO, SHARED, ThreadCpu, TreeCpu  # noqa: E402

TARGETS = {"default": {"sets_per_s": 5.0, "complete": 0.8, "to_3d_ms": 300.0, "to_page_ms": 400.0}}
TARGETS["fast"] = {"sets_per_s": 10.0}
GROUPS = (
    ("recorder (grab-*, write-*)", r"^(grab|write)-"),
    ("2D workers (live-keypoints*)", r"^live-keypoints"),
)


def make_mjpeg(demo: Path, folder: Path, fps: int = 30) -> list[Path]:
    """The demo's videos as MJPEG AVI at ``fps`` (every 60/fps-th frame), made once per folder."""
    import av

    out = []
    for c in CAMS:
        dst = folder / f"{c}.avi"
        out.append(dst)
        if dst.exists():
            continue
        with av.open(str(demo / "videos" / f"{c}.mp4")) as i, av.open(str(dst), "w") as o:
            s = i.streams.video[0]
            step = max(1, round(float(s.average_rate) / fps))
            os_ = o.add_stream("mjpeg", rate=fps)
            os_.width, os_.height, os_.pix_fmt = s.codec_context.width, s.codec_context.height, "yuvj420p"
            os_.options = {"q:v": "4"}
            n = 0
            for k, f in enumerate(i.decode(s)):
                if k % step:
                    continue
                g = f.reformat(format="yuvj420p")
                g.pts, g.time_base = n, Fraction(1, fps)
                for p in os_.encode(g):
                    o.mux(p)
                n += 1
            for p in os_.encode(None):
                o.mux(p)
    return out


def write_cams(folder: Path, videos: list[Path], preset: str) -> Path:
    cams = folder / f"cams_{preset}.yaml"
    live = f"live: {{preset: {preset}}}\n" if preset != "default" else ""
    cams.write_text(
        "calibration: rig.toml\ncameras:\n"
        + "".join(f"  - {{name: {v.stem}, source: '{v}', loop: true, realtime: true}}\n" for v in videos)
        + live
    )
    return cams


def jpegs(video: Path) -> list[bytes]:
    import av

    with av.open(str(video)) as c:
        return [bytes(p) for p in c.demux(c.streams.video[0]) if p.size]


def _checkout_has_jpeg_frames() -> bool:
    """Whether the roomcap on PYTHONPATH hands MJPEG frames on as JPEGs (this bench also runs on an older
    checkout, for the before/after: there the recorder decodes every frame and the stages are built first)."""
    from roomcap.capture.sources import Frame

    return "jpeg" in Frame.__dataclass_fields__


NEW = _checkout_has_jpeg_frames()


def decode_jpeg(data: bytes, reduce: int = 1):
    import cv2

    flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4}[reduce]
    return cv2.imdecode(np.frombuffer(data, np.uint8), flag)


def auto_reduce(w: int, h: int, setting: int) -> int:
    from roomcap.capture.config import auto_reduce as auto

    return auto(w, h, setting)


def jpeg_size(data: bytes) -> tuple[int, int]:
    img = decode_jpeg(data)
    return img.shape[1], img.shape[0]


def floor(videos: list[Path], cfg, folder: Path, n_sets: int = 24) -> dict:
    """Decoding cost (one thread) and the live 2D stage alone on the same frames, as the live loop runs it."""
    from roomcap.capture.live import LiveStep
    from roomcap.capture.session import SessionLayout
    from roomcap.capture.sources import Frame
    from roomcap.capture.sync import FrameSet
    from roomcap.pipeline.live import LiveContext, _keypoints

    frames = {v.stem: jpegs(v) for v in videos}
    r = auto_reduce(*jpeg_size(frames[CAMS[0]][0]), cfg.live.decode_reduce) if NEW else 1
    out: dict = {"reduce": r}
    for k in (1, r):
        t0 = time.perf_counter()
        n = 0
        for c in CAMS:
            for b in frames[c][:25]:
                decode_jpeg(b, k)
                n += 1
        out[f"decode_ms_per_frame_1/{k}"] = (time.perf_counter() - t0) * 1e3 / n
    stage = _keypoints(LiveContext(cfg, SessionLayout(folder / "floor"), None))
    try:
        times = []
        for t in range(n_sets):
            if NEW:  # the JPEGs, decoded by the stage (at 1/r)
                fs = {c: Frame(None, t, t, t, jpeg=frames[c][(2 * t) % len(frames[c])]) for c in CAMS}
            else:  # a checkout without JPEG frames: the recorder decoded them (full size), here timed too
                fs = {c: Frame(decode_jpeg(frames[c][(2 * t) % len(frames[c])]), t, t, t) for c in CAMS}
            step = LiveStep(FrameSet(t, t, fs), tuple(CAMS))
            if t == 1:  # the first set (cold crops, the detector on every camera) left out of the split
                for pipe in stage.pipes:
                    pipe.stage_s.clear()
                    for m in pipe.models:
                        m.run_s, m.run_cpu_s, m.n_runs = 0.0, 0.0, 0
            t0 = time.perf_counter()
            stage(step)
            times.append((time.perf_counter() - t0) * 1e3)
    finally:
        stage.close()
    split: dict[str, float] = {}
    runs: dict[str, float] = {}
    for pipe in stage.pipes:
        for k, v in pipe.stage_s.items():
            split[k] = split.get(k, 0.0) + v * 1e3 / (n_sets - 1)
        for m in pipe.models:
            runs[m.spec.name] = runs.get(m.spec.name, 0.0) + m.n_runs / (n_sets - 1)
    # thread-summed ms per set of the 2D's parts (the groups run in parallel: the sum exceeds the wall time)
    out["split_ms_per_set"] = dict(sorted(split.items(), key=lambda kv: -kv[1]))
    out["model_runs_per_set"] = runs
    out["live_2d_ms_per_set_first"] = times[0]
    out["live_2d_ms_per_set"] = float(np.median(times[1:]))
    out["sets_per_s_2d_allows"] = 1e3 / out["live_2d_ms_per_set"]
    return out


def reduced_accuracy(videos: list[Path], cfg, folder: Path, n_sets: int = 12) -> dict:
    """The live 2D stage on the same JPEG sets decoded at full size and at 1/2 and 1/4 (keypoints mapped
    back): the distance between the two results' keypoints (each person matched by the nearest mean
    keypoint, joints scored > 0.3 in both), px of the full-size image."""
    from dataclasses import replace

    from roomcap.capture.live import LiveStep
    from roomcap.capture.session import SessionLayout
    from roomcap.capture.sources import Frame
    from roomcap.capture.sync import FrameSet
    from roomcap.pipeline.live import LiveContext, _keypoints

    frames = {v.stem: jpegs(v) for v in videos}
    found = {}
    for r in (1, 2, 4):
        c = replace(cfg, live=replace(cfg.live, decode_reduce=r))
        stage = _keypoints(LiveContext(c, SessionLayout(folder / "accuracy"), None))
        try:
            found[r] = []
            for t in range(n_sets):
                step = LiveStep(
                    FrameSet(t, t, {k: Frame(None, t, t, t, jpeg=frames[k][t]) for k in CAMS}), CAMS
                )
                stage(step)
                found[r].append(step.outputs["detections"])
        finally:
            stage.close()
    out = {}
    for r in (2, 4):
        d = []
        for a_set, b_set in zip(found[1], found[r], strict=True):
            for cam in CAMS:
                a, b = a_set[cam], b_set[cam]
                for i in range(len(a.xy_px)):
                    if not len(b.xy_px):
                        continue
                    ca = np.nanmean(a.xy_px[i], 0)
                    j = int(np.argmin([np.linalg.norm(np.nanmean(p, 0) - ca) for p in b.xy_px]))
                    ok = (a.score[i] > 0.3) & (b.score[j] > 0.3)
                    d.extend(np.linalg.norm(a.xy_px[i][ok] - b.xy_px[j][ok], axis=1))
        d = np.asarray(d)
        out[f"1/{r}"] = {"median_px": float(np.median(d)), "p90_px": float(np.percentile(d, 90)), "n": len(d)}
    return out


def phase(name: str, cams_yaml: Path, folder: Path, seconds: float, browser: bool) -> dict:
    from roomcap.capture.config import load_config
    from roomcap.capture.live import LiveRunner
    from roomcap.capture.recorder import Recorder
    from roomcap.pipeline.live import build_stages
    from roomcap.pipeline.live_outputs import Outputs

    cfg = load_config(cams_yaml)
    sess = folder / f"S_{name}"
    if NEW:
        live = LiveRunner(cfg, sess, build_stages=build_stages, build_in_background=True)
    else:
        live = LiveRunner(cfg, sess, build_stages=build_stages)
    rec = Recorder(cfg, sess, duration_s=seconds, frameset_sink=live.queue, handle_signals=False, join=True)
    outputs = Outputs()
    p = argparse.ArgumentParser()
    outputs.add_arguments(p)
    close = outputs.open(p.parse_args(["--view", "--view-port", "0"]), live, rec)
    view = outputs.feed.view
    drive = None
    page_metrics: dict = {}  # the page's main-thread time by kind over the phase (DevTools metrics)
    chrome: list = []  # the browser's process, for its CPU (all its processes) over the phase
    if browser:
        from roomcap.pipeline.liveview.browser import HeadlessBrowser

        def run_browser() -> None:
            with HeadlessBrowser(folder / f"chrome-{name}", size_wh=(1400, 1000)) as b:
                chrome.append(b.proc.pid)
                b.open(view.url)
                b.call("Performance.enable", {})
                m0 = {m["name"]: m["value"] for m in b.call("Performance.getMetrics")["metrics"]}
                while not rec.stop_event.wait(0.5):
                    pass
                m1 = {m["name"]: m["value"] for m in b.call("Performance.getMetrics")["metrics"]}
                kinds = ("Duration", "Count")
                page_metrics.update({k: m1[k] - m0.get(k, 0.0) for k in m1 if k.endswith(kinds)})

        drive = threading.Thread(target=run_browser, daemon=True)
        drive.start()
    live.watch(rec.stop_event)
    live.start()
    load0 = os.getloadavg()[0]
    with ThreadCpu() as tc, TreeCpu(chrome) as browser_cpu:
        c0, w0 = time.process_time(), time.monotonic()
        summary = rec.run()
        live.stop()
        tc.sample()
        browser_cpu.sample()
        c1, w1 = time.process_time(), time.monotonic()
    if drive is not None:
        drive.join(30)
    acks = view.latency_ms()
    close()
    s = live.summary()
    rec_s = seconds
    ready_ns = getattr(live, "stages_ready_ns", None)
    ready_s = (ready_ns - rec.t0_ns) / 1e9 if ready_ns else None
    kp = live.stages.get("keypoints")
    dec = getattr(kp, "decode_ms", [0.0, 0])
    cams = summary["cameras"]
    res = {
        "preset": name,
        "seconds": rec_s,
        "processed": s["processed"],
        "sets_per_s": s["processed"] / rec_s,
        "sets_per_s_after_ready": s["processed"] / (rec_s - ready_s) if ready_s and ready_s < rec_s else None,
        "stages_ready_s": ready_s,
        "complete_share": s["complete"] / max(1, s["processed"]),
        "stale_dropped": s["skipped"],
        "to_3d_ms_median": s["latency_ms_median"],
        "to_3d_ms_p95": s["latency_ms_p95"],
        "to_page_ms_median": float(np.median(acks)) if acks else None,
        "page_acks": len(acks),
        "stage_ms_per_set": s["stage_ms_mean"],
        "decode_ms_per_frame_taken": dec[0] / dec[1] if dec[1] else None,
        "reduce": dict(getattr(kp, "reduce_of", {})),
        "process_cpu_per_s": (c1 - c0) / (w1 - w0),
        "cpu_s_per_s": {k: v / (w1 - w0) for k, v in tc.groups(GROUPS).items()},
        "browser_cpu_per_s": browser_cpu.used() / (w1 - w0) if chrome else None,
        "page_metrics": page_metrics,
        "browser_cpu_per_s_by_process": {k: v / (w1 - w0) for k, v in browser_cpu.by_kind().items()},
        "other_threads_cpu_per_s": {
            n: tc.used(n) / (w1 - w0)
            for n in sorted(tc.cpu, key=tc.used, reverse=True)
            if not any(re.match(pat, n) for _, pat in GROUPS)
            and n not in ("live", "live-3d")
            and tc.used(n) > 0.005 * (w1 - w0)
        },
        "frames_written": {c: cams[c].get("frames_written") for c in cams},
        "frames_grabbed": {c: cams[c].get("frames_grabbed") for c in cams},
        "recording": {c: cams[c].get("recording") for c in cams},
        "joined": all(cams[c].get("joined") for c in cams),
        "load_1min": [load0, os.getloadavg()[0]],
        "errors": s["errors"],
    }
    return res


def duration3(cams_yaml: Path, folder: Path) -> dict:
    """``python -m roomcap.pipeline.live --duration 3 --live`` as a user runs it: wall time launch -> exit."""
    out = folder / "S_duration3"
    cmd = [sys.executable, "-m", "roomcap.pipeline.live", "--cameras", str(cams_yaml), "--out", str(out)]
    cmd += ["--duration", "3", "--live", "--quiet"]
    t0 = time.monotonic()
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    wall = time.monotonic() - t0
    line = next((x.strip() for x in p.stdout.splitlines() if x.strip().startswith("live:")), "")
    return {"wall_s": wall, "rc": p.returncode, "live_line": line}


def _ms(v) -> str:
    return "n/a" if v is None else f"{v:.0f} ms"


def report(p: str, f: dict, ph: dict) -> list[str]:
    """The human lines of one preset: the floor, the live figures, the ratios, where the time goes."""
    t = TARGETS.get(p, {})
    r = f["reduce"]
    full, red = f["decode_ms_per_frame_1/1"], f[f"decode_ms_per_frame_1/{r}"]
    lines = [
        f"[{p}] floor: JPEG decode {full:.1f} ms full size, {red:.1f} ms at 1/{r}, per camera-frame; the 2D "
        f"alone {f['live_2d_ms_per_set']:.0f} ms per set of 4 (first {f['live_2d_ms_per_set_first']:.0f}) -> "
        f"at most {f['sets_per_s_2d_allows']:.1f} sets/s; its parts (ms per set, groups summed): "
        + ", ".join(f"{k} {v:.0f}" for k, v in f["split_ms_per_set"].items())
        + "; model runs per set: "
        + ", ".join(f"{k} {v:.1f}" for k, v in f["model_runs_per_set"].items()),
        f"[{p}] live: {ph['sets_per_s']:.2f} frame sets/s processed ({ph['processed']} in {ph['seconds']:g}"
        " s;"
        " "
        f"{ph['sets_per_s_after_ready'] or float('nan'):.2f}/s from the stages' ready at "
        f"{ph['stages_ready_s'] or float('nan'):.1f} s), {100 * ph['complete_share']:.0f} % complete, "
        f"capture->3D median {_ms(ph['to_3d_ms_median'])} (p95 {_ms(ph['to_3d_ms_p95'])}), "
        f"capture->page drawn median {_ms(ph['to_page_ms_median'])} ({ph['page_acks']} acks)",
    ]
    ratios = [f"sets/s / what the 2D alone allows {ph['sets_per_s'] / f['sets_per_s_2d_allows']:.2f}"]
    if "sets_per_s" in t:
        ratios.append(f"sets/s / target {t['sets_per_s']:g} {ph['sets_per_s'] / t['sets_per_s']:.2f}")
    if "complete" in t:
        ratios.append(
            f"complete / target {100 * t['complete']:.0f} % {ph['complete_share'] / t['complete']:.2f}"
        )
    if "to_3d_ms" in t:
        ratios.append(
            f"capture->3D / target {t['to_3d_ms']:g} ms {ph['to_3d_ms_median'] / t['to_3d_ms']:.2f}"
        )
    if "to_page_ms" in t and ph["to_page_ms_median"] is not None:
        ratios.append(
            f"capture->page / target {t['to_page_ms']:g} ms {ph['to_page_ms_median'] / t['to_page_ms']:.2f}"
        )
    lines.append(f"[{p}] ratios: " + "; ".join(ratios))
    st = ", ".join(f"{k} {v:.0f}" for k, v in ph["stage_ms_per_set"].items())
    cpu = ", ".join(f"{k} {v:.2f}" for k, v in ph["cpu_s_per_s"].items())
    dec = ph["decode_ms_per_frame_taken"]
    lines.append(
        f"[{p}] where a set's time goes: ms per set {st}; decoding a taken frame "
        f"{'n/a' if dec is None else f'{dec:.1f} ms'} (2D workers, reduce {ph['reduce']}); CPU s per s:"
        " "
        f"{cpu}; process {ph['process_cpu_per_s']:.2f}"
    )
    rec = next(iter(ph["recording"].values()))
    lines.append(
        f"[{p}] recorder: {sum(ph['frames_written'].values())} frames written of "
        f"{sum(ph['frames_grabbed'].values())} grabbed, joined {ph['joined']}; {rec}"
    )
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--shared", default=SHARED)
    ap.add_argument("--presets", default="default,fast")
    ap.add_argument(
        "--no-accuracy", action="store_true", help="skip the 2D on JPEGs at 1/2, 1/4 against full size"
    )
    ap.add_argument("--no-browser", action="store_true", help="no headless Chromium: no capture -> page")
    ap.add_argument(
        "--work", default=None, help="folder for the MJPEG files and sessions (default: temporary)"
    )
    args = ap.parse_args()
    os.environ.setdefault("ROOMCAP_SHARED", args.shared)
    from roomcap.calibrate.formats import import_rig
    from roomcap.capture.config import load_config

    demo = Path(args.shared) / DEMO
    if not demo.exists():
        sys.exit(f"bench_live_usb: {demo} not found; set --shared")
    browser = not args.no_browser
    if browser:
        from roomcap.pipeline.liveview.browser import find_chromium

        browser = find_chromium() is not None
    folder = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_live_usb_"))
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("S_*"):
        import shutil

        shutil.rmtree(old)
    import_rig(demo / "calibration" / "Calib.qca.txt").save(folder / "rig.toml")
    videos = make_mjpeg(demo, folder)
    load_start = os.getloadavg()
    presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    yamls = {p: write_cams(folder, videos, p) for p in presets}
    res: dict = {"cores": os.cpu_count(), "load_start": load_start, "seconds": args.seconds}
    res["checkout"] = str(Path(__import__("roomcap").__path__[0]).resolve())
    res["jpeg_frames"] = NEW
    res["floor"] = {p: floor(videos, load_config(yamls[p]), folder) for p in presets}
    if not args.no_accuracy and NEW:
        res["reduced_accuracy"] = reduced_accuracy(videos, load_config(yamls[presets[0]]), folder)
    res["phases"] = {p: phase(p, yamls[p], folder, args.seconds, browser) for p in presets}
    res["duration3"] = duration3(yamls[presets[0]], folder)
    res["load_end"] = os.getloadavg()
    # -- the report
    lo = f"load average {load_start[0]:.1f} at the start, {res['load_end'][0]:.1f} at the end"
    print(f"{os.cpu_count()} cores; {lo}; 4 MJPEG cameras 1088x1920 at 30 fps, {args.seconds:g} s per preset")
    for p in presets:
        print("\n".join(report(p, res["floor"][p], res["phases"][p])))
    for k, v in res.get("reduced_accuracy", {}).items():
        print(
            f"[{presets[0]}] 2D on JPEGs decoded at {k} against full size: keypoints {v['median_px']:.2f} px "
            f"apart (median; p90 {v['p90_px']:.2f} px; {v['n']} joints), full-size pixels"
        )
    d3 = res["duration3"]
    print(
        f"--duration 3 (python -m roomcap.pipeline.live ... --live --quiet): {d3['wall_s']:.2f} s launch -> "
        f"exit (target 4.5 s: ratio {d3['wall_s'] / 4.5:.2f}), rc {d3['rc']}; {d3['live_line']}"
    )
    print("BENCH " + json.dumps(res, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
