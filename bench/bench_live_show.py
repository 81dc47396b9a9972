"""Show the live page as a user gets it: ``python -m roomcap.pipeline.live --live --view`` run as a command,
a headless Chromium on its page, screenshots and the command's own log.

Two runs, each a separate ``capture-run`` process (its output, stderr included, is the log):

1. ``empty``: 2 ``synthetic:`` cameras (a moving texture with nobody in it: an empty room), the ring rig of
   ``roomcap.synthetic.rigs`` as calibration, the default live stages (the real 2D model, triangulate,
   track) for ``--empty-seconds``; a screenshot once both camera images are drawn and the page says
   "nobody in view"; the tracebacks in the log are counted (must be 0).
2. ``demo``: the Pose2Sim multi-person demo's 4 videos as looping file cameras (``bench/_live_demo.py``) with
   the real default 2D model (no precomputed 2D), ``--stream lsl`` and the page (the live forecast on, the
   default) for ``--seconds``; an LSL inlet on loopback (``LSL_API_CFG``: ``ResolveScope = machine``) reads
   every sample. Reported: the live track file (path, frames, track ids), LSL samples against the frame
   sets processed (the summary line) and against the track file's frames (each sample's timestamp matched
   to a frame's ``t_ns``), and a screenshot once the page draws tracked people with their forecast (path
   and ghost skeleton), or at 90 % of the run when it never did (said in the summary).

Writes ``empty_room.png``, ``demo_forecast.png`` (the page), ``demo_forecast_room.png`` (its 3D view of the
room zoomed in 2.1x, when people with a forecast are in view), the two logs and ``summary.json`` under
``--out``.

    python bench/bench_live_show.py [--out /tmp/live_show] [--seconds 20] [--empty-seconds 10]
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).parent))

from _live_demo import DEMO, SHARED, LslReader, loopback_lsl, match_lsl_to_frames, write_looping_cams  # noqa: E402

URL = re.compile(r"live view: (http\S+)")
SUMMARY = re.compile(r"live: (\d+) frame sets processed \((\d+) stale ones dropped, (\d+) complete\)")
LATENCY = re.compile(r"latency median ([\d.]+) ms, p95 ([\d.]+) ms")


class LiveCommand:
    """``python -m roomcap.pipeline.live`` with ``argv`` in a process of its own; its stdout and stderr go to
    ``log`` (and ``lines``); ``url`` is set when it prints the page's address."""

    def __init__(self, argv: list[str], log: Path):
        self.log = log
        self.lines: list[str] = []
        self.url: str | None = None
        self.got_url = threading.Event()
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "roomcap.pipeline.live", *argv],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
        )
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        with self.log.open("w") as f:
            for line in self.proc.stdout:
                f.write(line)
                f.flush()
                self.lines.append(line)
                m = URL.search(line)
                if m and self.url is None:
                    self.url = m.group(1)
                    self.got_url.set()
        self.got_url.set()  # ended without a page

    def alive(self) -> bool:
        return self.proc.poll() is None

    def wait(self, timeout_s: float) -> int:
        try:
            rc = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait(10)
        self._t.join(10)
        return rc

    def text(self) -> str:
        return "".join(self.lines)

    def figures(self) -> dict:
        txt = self.text()
        m = SUMMARY.search(txt)
        lat = LATENCY.search(txt)
        return {
            "processed": int(m.group(1)) if m else None,
            "stale_dropped": int(m.group(2)) if m else None,
            "complete": int(m.group(3)) if m else None,
            "latency_ms_median": float(lat.group(1)) if lat else None,
            "latency_ms_p95": float(lat.group(2)) if lat else None,
            "tracebacks": txt.count("Traceback (most recent call last)"),
            "errors_logged": len(re.findall(r"\bERROR\b", txt)),
            "summary_line": next((ln.strip() for ln in self.lines if "frame sets processed" in ln), None),
        }


def _page(b) -> dict:
    """What the page shows now (its ``data-*`` readouts)."""
    d = b.evaluate("JSON.stringify(document.body.dataset)") or "{}"
    d = json.loads(d)
    d["who"] = b.evaluate("document.getElementById('who').textContent")
    return d


def drive_page(
    cmd: LiveCommand,
    profile: Path,
    png: Path,
    ready: str,
    latest_s: float,
    room_png: Path | None = None,
    earliest_s: float = 0.0,
) -> dict:
    """Open the command's page in a headless Chromium; a screenshot when the JavaScript ``ready`` is true
    (checked 4 times a second; kept if the page still shows the same frame set after it), else at
    ``latest_s`` after the page opened. The page's readouts at that moment, when, and its own errors.
    ``room_png``: then also the room's 3D view zoomed in, when ``ready`` holds again. ``earliest_s``: not
    before (the page's per-camera rates need a second of frames)."""
    from roomcap.pipeline.liveview.browser import HeadlessBrowser

    cmd.got_url.wait(120)
    if cmd.url is None:
        return {"error": "the command printed no page address"}
    with HeadlessBrowser(profile, size_wh=(1500, 1150)) as b:
        b.open(cmd.url)
        t0 = time.monotonic()
        res: dict = {"error": "the command ended before the screenshot"}

        def check() -> bool:
            try:
                return bool(b.evaluate(ready))
            except Exception:  # noqa: BLE001 - the page may be between loads: try again
                return False

        while cmd.alive():
            met = time.monotonic() - t0 >= earliest_s and check()
            if met or time.monotonic() - t0 > latest_s:
                frame = b.evaluate("document.body.dataset.frame")
                b.screenshot(png)
                page = _page(b)
                # the page may have drawn a newer update while the screenshot was taken: keep the shot
                # only if the page still shows the same frame set (else try again, this one kept meanwhile)
                met = met and page.get("frame") == frame and check()
                res = {
                    "screenshot": str(png),
                    "condition_met": met,
                    "at_s_after_page_open": round(time.monotonic() - t0, 1),
                    "at_s_after_start": round(time.monotonic() - cmd.t0, 1),
                    "page": page,
                }
                if met or time.monotonic() - t0 > latest_s:
                    break
            time.sleep(0.25)
        if room_png is not None and res.get("condition_met"):
            res["room"] = _room_closeup(b, cmd, room_png, check)
        res["page_errors"] = b.page_errors[:5]
        return res


ZOOM_STEPS = 8  # wheel steps on the room's 3D view (1.1x each: 2.1x)


def _room_closeup(b, cmd: LiveCommand, png: Path, check) -> dict:
    """The room's 3D view alone, zoomed in (the page's own wheel zoom), when ``check`` holds for the frame
    set it shows: the forecast paths and ghost skeletons at a size one can see."""
    b.evaluate(
        f"for (let i = 0; i < {ZOOM_STEPS}; i++) document.getElementById('room').dispatchEvent("
        "new WheelEvent('wheel', {deltaY: -100, cancelable: true}))"
    )
    r = json.loads(b.evaluate("JSON.stringify(document.getElementById('room').getBoundingClientRect())"))
    clip = {"x": r["x"], "y": r["y"], "width": r["width"], "height": r["height"], "scale": 1}
    while cmd.alive():
        frame = b.evaluate("document.body.dataset.frame")
        if check():
            shot = b.call("Page.captureScreenshot", {"format": "png", "clip": clip})
            if b.evaluate("document.body.dataset.frame") == frame and check():
                png.write_bytes(base64.b64decode(shot["data"]))
                return {"screenshot": str(png), "zoom": 1.1**ZOOM_STEPS, "page": _page(b)}
        time.sleep(0.25)
    return {"error": "the command ended before the room's close-up"}


def empty_room(out: Path, tmp: Path, seconds: float) -> dict:
    from roomcap.synthetic.rigs import ring_rig

    rig = ring_rig(2, radius_m=4.0, size_wh=(640, 480))
    rig.save(tmp / "rig.toml")
    cams = tmp / "cams_empty.yaml"
    cams.write_text(
        "calibration: rig.toml\ncameras:\n"
        + "".join(
            f"  - {{name: {c.name}, source: 'synthetic:?offset_ms={i}', resolution: [640, 480], fps: 15}}\n"
            for i, c in enumerate(rig.cameras)
        )
    )
    argv = ["--cameras", str(cams), "--out", str(tmp / "empty"), "--duration", f"{seconds:g}"]
    argv += ["--live", "--view", "--view-port", "0", "--quiet"]
    cmd = LiveCommand(argv, out / "empty_room.log")
    shot = drive_page(
        cmd,
        tmp / "chrome-empty",
        out / "empty_room.png",
        "document.body.dataset.panesDrawn === '2' && document.body.dataset.nobody === 'nobody in view' "
        "&& Number(document.body.dataset.frame) > 0",
        0.8 * seconds,
        earliest_s=0.4 * seconds,
    )
    rc = cmd.wait(seconds + 120)
    return {"command": "python -m roomcap.pipeline.live " + " ".join(argv), "rc": rc, **cmd.figures(), **shot}


def demo(out: Path, tmp: Path, shared: Path, seconds: float) -> dict:
    from roomcap.capture.session import SessionLayout
    from roomcap.track.trackfile import TrackFile

    demo_dir = shared / DEMO
    if not demo_dir.exists():
        return {"skipped": f"{demo_dir} not found; set --shared to the shared data folder"}
    cams = write_looping_cams(demo_dir, tmp)
    sess = tmp / "demo"
    argv = ["--cameras", str(cams), "--out", str(sess), "--duration", f"{seconds:g}"]
    argv += ["--live", "--view", "--view-port", "0", "--stream", "lsl", "--quiet", "--no-join"]
    cmd = LiveCommand(argv, out / "demo.log")
    lsl = LslReader(f"roomcap-{sess.name}", resolve_s=120.0).start()
    shot = drive_page(
        cmd,
        tmp / "chrome-demo",
        out / "demo_forecast.png",
        "Number(document.body.dataset.people) > 0 && Number(document.body.dataset.forecastDrawn) > 0 "
        "&& document.body.dataset.panesDrawn === '4'",
        0.9 * seconds + 10.0,  # the page opens while the 2D model loads: a few seconds before the first set
        room_png=out / "demo_forecast_room.png",
    )
    rc = cmd.wait(seconds + 180)
    lsl.stop()
    res = {"command": "python -m roomcap.pipeline.live " + " ".join(argv), "rc": rc, **cmd.figures(), **shot}
    lay = SessionLayout(sess)
    track = {"path": str(lay.live_tracks), "exists": False}
    tf = None
    try:
        tf = TrackFile.load(lay.live_tracks)
    except Exception as e:  # noqa: BLE001 - reported, not raised: the figure is whether it was written
        track["error"] = f"{type(e).__name__}: {e}"
    if tf is not None:
        present = np.isfinite(tf.xyz_m).all(-1).any(-1)  # (T, K): the track has a joint in that frame
        track.update(
            exists=True,
            frames=int(tf.n_frames),
            frames_with_people=int(present.any(1).sum()),
            track_ids=[int(t) for t in tf.track_id],
            frames_per_track={int(t): int(present[:, k].sum()) for k, t in enumerate(tf.track_id)},
        )
    res["live_track"] = track
    res["lsl"] = _lsl_against(lsl, tf, res.get("processed"))
    return res


def _lsl_against(lsl: LslReader, tf, processed: int | None) -> dict:
    """The samples the inlet got against the processed sets and the track file's frames, each sample
    matched to a frame by its timestamp (:func:`_live_demo.match_lsl_to_frames`); a sample with no frame
    is a set the track stage skipped (late, out of order), sent with nobody."""
    res: dict = {"samples": lsl.n, "processed": processed, "inlet_open": lsl.connected_at is not None}
    if processed is not None:
        res["samples_equal_processed"] = lsl.n == processed
    if tf is None or not lsl.ts:
        return res
    row, err = match_lsl_to_frames(lsl.ts, tf.t_ns)
    ok = row >= 0
    first = int(row[0]) if ok[0] else None
    got = set(row[ok].tolist())
    missing = [int(tf.frame_index[i]) for i in range(first or 0, tf.n_frames) if i not in got]
    arr = np.asarray(lsl.rows, np.float32)
    # S slots x 19 joints x 4 values, then S track id channels (body19): a sample with no id is nobody
    per_slot = 19 * 4 + 1
    ids = arr[:, -(arr.shape[1] // per_slot) :] if arr.shape[1] % per_slot == 0 else None
    nobody = (~np.isfinite(ids)).all(1) if ids is not None else None
    res.update(
        matched_to_track_frames=int(ok.sum()),
        track_frames=int(tf.n_frames),
        track_frames_before_inlet=first,
        track_frames_since_inlet_without_sample=missing[:20],
        n_without_sample=len(missing),
        match_error_ms_max=float(err[ok].max()) if ok.any() else None,
        samples_with_nobody=int(nobody.sum()) if nobody is not None else None,
        unmatched_samples_with_nobody=int(nobody[~ok].sum()) if nobody is not None else None,
    )
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="/tmp/live_show", help="folder for the PNGs, logs and summary.json")
    ap.add_argument("--seconds", type=float, default=20.0, help="the demo run's --duration")
    ap.add_argument("--empty-seconds", type=float, default=10.0, help="the empty room's --duration")
    ap.add_argument("--shared", default=SHARED)
    ap.add_argument("--skip-empty", action="store_true")
    ap.add_argument("--skip-demo", action="store_true")
    args = ap.parse_args()
    from roomcap.pipeline.liveview.browser import find_chromium

    if find_chromium() is None:
        sys.exit("bench_live_show: no headless Chromium (apt-get install chromium)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "work"
    tmp.mkdir(exist_ok=True)
    loopback_lsl(tmp)  # before pylsl loads, here and in the commands this starts
    res: dict = {"load_1min_start": os.getloadavg()[0], "cpus": os.cpu_count()}
    if not args.skip_empty:
        e = res["empty"] = empty_room(out, tmp, args.empty_seconds)
        print(
            f"empty room ({args.empty_seconds:g} s, 2 synthetic cameras, real 2D): rc {e['rc']}, "
            f"{e['processed']} frame sets processed, tracebacks {e['tracebacks']}, page "
            f"{ {k: e.get('page', {}).get(k) for k in ('panesDrawn', 'people', 'nobody', 'frame')} }, "
            f"screenshot {e.get('screenshot')} (condition met: {e.get('condition_met')})",
            flush=True,
        )
    if not args.skip_demo:
        d = res["demo"] = demo(out, tmp, Path(args.shared), args.seconds)
        if "skipped" in d:
            print("demo: " + d["skipped"])
        else:
            lt, ls = d["live_track"], d["lsl"]
            print(
                f"demo ({args.seconds:g} s, 4 looping file cameras, real 2D, --stream lsl): rc {d['rc']}, "
                f"{d['processed']} frame sets processed ({d['complete']} complete, {d['stale_dropped']} "
                f"stale dropped), latency median {d['latency_ms_median']} ms; tracebacks {d['tracebacks']}; "
                "live track "
                f"{lt['path']}: {lt.get('frames')} frames ({lt.get('frames_with_people')} with people), ids "
                f"{lt.get('track_ids')}; LSL samples {ls['samples']} vs processed {ls['processed']} "
                f"(track frames without a sample since the inlet opened: {ls.get('n_without_sample')}; "
                f"samples with nobody {ls.get('samples_with_nobody')}); page at the screenshot "
                f"{ {k: d.get('page', {}).get(k) for k in ('people', 'forecastDrawn', 'panesDrawn')} }, "
                f"screenshot {d.get('screenshot')} (condition met: {d.get('condition_met')})",
                flush=True,
            )
    res["load_1min_end"] = os.getloadavg()[0]
    (out / "summary.json").write_text(json.dumps(res, indent=1))
    print(f"load average {res['load_1min_start']:.2f} -> {res['load_1min_end']:.2f}; {out / 'summary.json'}")
    print("BENCH " + json.dumps(res))


if __name__ == "__main__":
    main()
