"""``capture-run --live``: the runner that passes every synchronised frame set through stages.

A live step is a batch of one frame set (ARCHITECTURE.md: live and batch run the same stage code). The
stages are plain callables ``stage(step) -> None`` that read and write ``step.outputs``; a stage may
have a ``close()`` that the runner calls when the recording ends. The stages that use the later
packages (keypoints, triangulation, tracking) are built in :mod:`roomcap.pipeline.live` (the stage order:
capture sits below them) and handed in as ``stages`` or ``build_stages``.

The runner keeps up rather than falling behind: when several sets are ready it processes the
newest and counts the others as skipped (the recording itself never waits for live processing).
Latency = end of processing - host arrival of the newest frame in the set.
"""

from __future__ import annotations

import argparse
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from roomcap.capture.config import CaptureConfig
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import host_now_ns
from roomcap.capture.sync import FrameSet, Synchroniser

log = logging.getLogger(__name__)


@dataclass
class LiveStep:
    frameset: FrameSet
    cameras: tuple[str, ...]
    outputs: dict = field(default_factory=dict)  # stage results: "detections", "poses3d", "tracks", ...


Stage = Callable[[LiveStep], None]
BuildStages = Callable[[CaptureConfig, SessionLayout], "tuple[dict[str, Stage], dict[str, str]]"]


class LiveOutputs(Protocol):
    """What ``capture-run --live`` sends out while it records (the live view, network streams, a Rerun
    recording), built above capture (:mod:`roomcap.pipeline.live_outputs`) and handed to ``capture.cli``."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add the command-line options (``--view``, ``--stream``, ...)."""

    def open(self, args: argparse.Namespace, runner: LiveRunner | None, recorder: Any) -> Callable[[], None]:
        """Check the options and open the outputs before the recording starts (bad input raises a
        ``RoomcapError`` and nothing is recorded); returns the function that closes them."""
        ...


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
        self,
        cfg: CaptureConfig,
        out,
        stages: dict[str, Stage] | None = None,
        queue_size: int = 256,
        build_stages: BuildStages | None = None,
    ):
        self.cfg = cfg
        self.layout = SessionLayout(out)
        self.queue: queue.Queue = queue.Queue(maxsize=queue_size)
        fps = max(c.fps or 30.0 for c in cfg.cameras)
        self.sync = Synchroniser(cfg.names, cfg.sync.tolerance_ns(fps), int(cfg.sync.max_wait_ms * 1e6))
        self.stats = LiveStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if stages is None:
            stages, errors = build_stages(cfg, self.layout) if build_stages is not None else ({}, {})
            self.stats.errors.update(errors)
        self.stages = stages
        self.stats.stage_ms = {k: 0.0 for k in self.stages}
        self.on_step: Callable[[LiveStep], None] | None = None  # e.g. a viewer

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
        for name, stage in self.stages.items():  # e.g. the track stage writes its last part
            close = getattr(stage, "close", None)
            if close is not None:
                try:
                    close()
                except Exception as e:  # noqa: BLE001 - reported like a failing step
                    log.exception("live: closing stage %r failed", name)
                    self.stats.errors[name] = f"{type(e).__name__}: {e}"
        if "track" in self.stages and self.stats.processed:
            log.info("live: track parts in %s", self.layout.live_tracks.with_suffix(".parts"))

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
