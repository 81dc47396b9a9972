"""``capture-run --live``: every synchronised frame set through the batch pipeline's own functions.

A live step is a batch of one frame set (DESIGN.md, "one code path for live and batch"). The
stages are plain callables ``stage(step) -> None`` that read and write ``step.outputs``; each
entry of ``STAGES`` builds one from the same functions the batch stages call. Adding a stage is
one line in ``STAGES``. A stage whose package is not importable yet is skipped with a warning.

The runner keeps up rather than falling behind: when several sets are ready it processes the
newest and counts the others as skipped (the recording itself never waits for live processing).
Latency = end of processing - host arrival of the newest frame in the set.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from capture.config import CaptureConfig
from capture.session import SessionLayout
from capture.sources import host_now_ns
from capture.sync import FrameSet, Synchroniser
from keypoints.skeletons import CANONICAL
from triangulate.reconstruct import FrameReconstructor
from triangulate.tracker import track_poses

log = logging.getLogger(__name__)


@dataclass
class LiveStep:
    frameset: FrameSet
    cameras: tuple[str, ...]
    outputs: dict = field(default_factory=dict)  # stage results: "detections", "poses3d", "tracks", ...


Stage = Callable[[LiveStep], None]


@dataclass
class LiveContext:
    cfg: CaptureConfig
    layout: SessionLayout
    rig: object | None  # calibrate.camera.CameraRig when cams.yaml names a calibration


# ----------------------------------------------------------------------------- stages (batch functions)


def _keypoints(ctx: LiveContext) -> Stage:
    from keypoints.pipeline import KeypointPipeline  # lazy: loads onnxruntime

    pipe = KeypointPipeline()

    def stage(step: LiveStep) -> None:
        frames = [step.frameset.frames[c] for c in step.cameras]
        present = [i for i, f in enumerate(frames) if f is not None and f.image is not None]
        results = pipe([frames[i].image for i in present])
        step.outputs["detections"] = {step.cameras[i]: r for i, r in zip(present, results, strict=True)}

    return stage


def _triangulate(ctx: LiveContext) -> Stage:

    if ctx.rig is None:
        raise RuntimeError(
            "triangulation needs a calibration: set 'calibration: path/to/rig.toml' in cams.yaml"
        )
    rig = ctx.rig.subset(list(ctx.cfg.names))
    rec = FrameReconstructor(
        rig.projection_matrices(), rig.fundamental_matrices(), None, None, CANONICAL.joint_names
    )
    J = CANONICAL.n_joints

    def stage(step: LiveStep) -> None:
        dets = step.outputs.get("detections", {})
        P = max([len(d.xy_px) for d in dets.values()], default=0)
        C = len(step.cameras)
        xy = np.full((C, P, J, 2), np.nan)
        sc = np.zeros((C, P, J))
        for c, cam in enumerate(step.cameras):
            d = dets.get(cam)
            if d is not None and len(d.xy_px):
                xy[c, : len(d.xy_px)] = rig[cam].undistort_px(d.xy_px)
                sc[c, : len(d.xy_px)] = d.score
        step.outputs["poses3d"] = rec(xy, sc)

    return stage


def _track(ctx: LiveContext) -> Stage:

    hist_xyz: list[np.ndarray] = []
    hist_t: list[int] = []
    fps = max(c.fps or 30.0 for c in ctx.cfg.cameras)
    state = {"last_write": 0.0}

    def stage(step: LiveStep) -> None:
        poses = step.outputs.get("poses3d")
        hist_xyz.append(np.zeros((0, CANONICAL.n_joints, 3)) if poses is None else poses.xyz_m)
        hist_t.append(step.frameset.t_ns)
        if time.monotonic() - state["last_write"] < 2.0 and not step.outputs.get("final"):
            return
        P = max(1, max(len(x) for x in hist_xyz))
        X = np.full((len(hist_xyz), P, CANONICAL.n_joints, 3), np.nan)
        for t, x in enumerate(hist_xyz):
            X[t, : len(x)] = x
        tf = track_poses(
            X,
            np.arange(len(X)),
            np.asarray(hist_t, np.int64),
            fps,
            CANONICAL.joint_names,
            np.asarray(CANONICAL.parents),
            source="capture.live (triangulate.tracker)",
        )
        tf.save(ctx.layout.tracks)  # atomic: a reader always sees a whole file
        state["last_write"] = time.monotonic()
        step.outputs["tracks"] = tf

    return stage


# the live pipeline: one line per stage, same functions as the batch stages
STAGES: dict[str, Callable[[LiveContext], Stage]] = {
    "keypoints": _keypoints,
    "triangulate": _triangulate,
    "track": _track,
}


# ----------------------------------------------------------------------------- runner


@dataclass
class LiveStats:
    sets: int = 0
    processed: int = 0
    skipped: int = 0
    complete: int = 0
    latency_ms: list[float] = field(default_factory=list)
    stage_ms: dict[str, float] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)


class LiveRunner:
    """Consumes (cam, frame) from ``queue``, synchronises, runs the stages on each frame set."""

    def __init__(
        self, cfg: CaptureConfig, out, stages: dict[str, Stage] | None = None, queue_size: int = 256
    ):
        self.cfg = cfg
        self.layout = SessionLayout(out)
        self.queue: queue.Queue = queue.Queue(maxsize=queue_size)
        fps = max(c.fps or 30.0 for c in cfg.cameras)
        self.sync = Synchroniser(cfg.names, cfg.sync.tolerance_ns(fps), int(cfg.sync.max_wait_ms * 1e6))
        self.stats = LiveStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stages = stages if stages is not None else self._build_stages()
        self.stats.stage_ms = {k: 0.0 for k in self.stages}
        self.on_step: Callable[[LiveStep], None] | None = None  # e.g. a viewer

    def _build_stages(self) -> dict[str, Stage]:
        rig = None
        if self.cfg.calibration:
            try:
                from calibrate.camera import CameraRig

                p = Path(self.cfg.calibration)
                if not p.is_absolute() and self.cfg.path:
                    p = Path(self.cfg.path).parent / p
                rig = CameraRig.load(p)
            except Exception as e:  # live keeps recording without 3D
                log.warning(
                    "live: cannot load calibration %s (%s); 3D stages are off", self.cfg.calibration, e
                )
        ctx = LiveContext(self.cfg, self.layout, rig)
        out = {}
        for name in self.cfg.live.stages:
            try:
                out[name] = STAGES[name](ctx)
            except Exception as e:
                log.warning("live: stage %r is not available (%s); skipping it", name, e)
                self.stats.errors[name] = str(e)
        return out

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="live", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        """Call after the recorder returned: processes what is left, then ends the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _drain(self) -> bool:
        got = False
        while True:
            try:
                cam, frame = self.queue.get(timeout=0.02 if not got else 0)
            except queue.Empty:
                return got
            self.sync.push(cam, frame)
            got = True

    def _run(self) -> None:
        every = self.cfg.live.every_n
        while True:
            stopping = self._stop.is_set()
            self._drain()
            ready = self.sync.pop_ready(host_now_ns(), flush=stopping)
            self.stats.sets += len(ready)
            if len(ready) > 1 and not stopping:
                self.stats.skipped += len(ready) - 1
                ready = ready[-1:]
            for fs in ready:
                if fs.index % every:
                    continue
                self.process(fs, final=stopping and fs is ready[-1])
            if stopping and self.queue.empty():
                break
        if "track" in self.stages and self.stats.processed:
            log.info("live: track file %s", self.layout.tracks)

    def process(self, fs: FrameSet, final: bool = False) -> LiveStep:
        step = LiveStep(fs, self.cfg.names, {"final": final})
        for name, stage in self.stages.items():
            t0 = time.perf_counter()
            try:
                stage(step)
            except Exception as e:
                if name not in self.stats.errors:
                    log.exception("live: stage %r failed", name)
                self.stats.errors[name] = f"{type(e).__name__}: {e}"
            self.stats.stage_ms[name] = self.stats.stage_ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3
        newest = max(f.t_host_ns for f in fs.frames.values() if f is not None)
        self.stats.latency_ms.append((host_now_ns() - newest) / 1e6)
        self.stats.processed += 1
        self.stats.complete += fs.complete
        if self.on_step:
            self.on_step(step)
        return step

    def summary(self) -> dict:
        lat = np.asarray(self.stats.latency_ms) if self.stats.latency_ms else np.asarray([np.nan])
        n = max(1, self.stats.processed)
        return {
            "sets": self.stats.sets,
            "processed": self.stats.processed,
            "skipped": self.stats.skipped,
            "complete": self.stats.complete,
            "latency_ms_median": float(np.median(lat)),
            "latency_ms_p95": float(np.percentile(lat, 95)),
            "stage_ms_mean": {k: v / n for k, v in self.stats.stage_ms.items()},
            "errors": dict(self.stats.errors),
        }

    def summary_line(self) -> str:
        s = self.summary()
        stages = ", ".join(f"{k} {v:.1f} ms" for k, v in s["stage_ms_mean"].items()) or "no stages"
        return (
            f"{s['processed']} frame sets processed ({s['skipped']} skipped, {s['complete']} complete), "
            f"latency median {s['latency_ms_median']:.1f} ms, p95 {s['latency_ms_p95']:.1f} ms; {stages}"
        )
