"""``capture-run --live``: the runner that passes every synchronised frame set through stages.

A live step is a batch of one frame set (ARCHITECTURE.md: live and batch run the same stage code). The
stages are plain callables ``stage(step) -> None`` that read and write ``step.outputs``; a stage may
have a ``close()`` that the runner calls when the recording ends. The stages that use the later
packages (keypoints, triangulation, tracking) are built in :mod:`roomcap.pipeline.live` (the stage order:
capture sits below them) and handed in as ``stages`` or ``build_stages``.

The runner keeps up rather than falling behind: it processes the newest ready frame set and drops (and
counts as skipped) the ones a newer set replaced before they were taken; its queue holds a few frames per
camera, never seconds of them, and a stop ends it after the set in hand (the recording itself never waits
for live processing). Latency = end of processing - host arrival of the newest frame in the set.
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

QUEUE_FRAMES_PER_CAMERA = 8  # the live queue's bound: a few frames per camera, never seconds of them
SYNC_POLL_S = 0.01  # the sync thread's longest wait for a frame (and the live thread's for a stop)


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
    # jumps of the sources' clock a stage met (``step.outputs["jump"]``: the track stage starts a new segment)
    jumps: list[dict] = field(default_factory=list)


class LiveRunner:
    """Consumes (cam, frame) from ``queue``, synchronises, runs the stages on the newest frame set.

    Two threads, so that nothing piles up while a stage runs: ``live-sync`` drains the bounded ``queue``
    into the :class:`Synchroniser` every few ms and keeps only the newest ready frame set in a one-set
    slot (a complete set is preferred: an incomplete one never replaces a complete one not yet taken); a
    set replaced before it was taken is stale, dropped and counted (``stats.skipped``). ``live`` takes
    the set in the slot and runs the first stage (the 2D) on it, then hands it to ``live-3d`` for the
    others (triangulation, tracking, the outputs) and takes the next set meanwhile (``pipelined``; in
    order, one set handed over at a time). The queue holds a few frames per camera (``queue_size``,
    default 8 per camera; a full queue drops the frame, counted by the grabber as ``dropped_live``), so
    the live loop never falls further behind than one frame set plus the two being processed.

    Stopping (:meth:`stop`, or the ``stop_event`` handed to :meth:`watch`: the recorder's, set by
    ``--duration``, Ctrl-C or the sources' end): the sets being processed are finished, the rest is
    dropped (counted), the stages are closed. Nothing queued is processed after the stop.
    """

    def __init__(
        self,
        cfg: CaptureConfig,
        out,
        stages: dict[str, Stage] | None = None,
        queue_size: int | None = None,
        build_stages: BuildStages | None = None,
        build_in_background: bool = False,
    ):
        self.cfg = cfg
        self.layout = SessionLayout(out)
        size = queue_size if queue_size is not None else QUEUE_FRAMES_PER_CAMERA * len(cfg.cameras)
        self.queue: queue.Queue = queue.Queue(maxsize=size)
        fps = max(c.fps or 30.0 for c in cfg.cameras)
        self.sync = Synchroniser(cfg.names, cfg.sync.tolerance_ns(fps), int(cfg.sync.max_wait_ms * 1e6))
        self.stats = LiveStats()
        self._stop = threading.Event()
        self._watched: threading.Event | None = None
        self._slot: FrameSet | None = None  # the newest ready frame set, not yet taken
        self._cond = threading.Condition()
        self._threads: list[threading.Thread] = []
        self.stopped_ns: int | None = None  # host_now_ns when the stop was seen
        self.ended_ns: int | None = None  # host_now_ns when the live loop ended (stages closed)
        # build_in_background: the stages (the 2D models' load and warm-up, the tracker's imports) are built
        # on the live thread while the recording starts, not before it; the sets that come meanwhile are
        # dropped as stale (counted); ``stages_ready_ns`` says when they were ready
        self._build = build_stages if stages is None and build_in_background else None
        self.stages_ready_ns: int | None = None
        if stages is None and self._build is None:
            stages, errors = build_stages(cfg, self.layout) if build_stages is not None else ({}, {})
            self.stats.errors.update(errors)
        self.stages = stages or {}
        self.planned = tuple(self.stages) if self._build is None else tuple(cfg.live.stages)
        self.stats.stage_ms = {k: 0.0 for k in self.stages}
        self.on_step: Callable[[LiveStep], None] | None = None  # e.g. a viewer
        # the first stage (the 2D) of a set overlaps the others of the previous set (_run_pipelined)
        self.pipelined = True
        self.reports: list[Callable[[], str]] = []  # more of the summary line (e.g. the forecast's cost)

    def watch(self, stop_event: threading.Event) -> None:
        """End the live loop as soon as ``stop_event`` is set (the recorder's: the duration reached, a
        signal, the sources' end), not only when :meth:`stop` is called after the recording's join."""
        self._watched = stop_event

    @property
    def stopping(self) -> bool:
        return self._stop.is_set() or (self._watched is not None and self._watched.is_set())

    def start(self) -> None:
        self._threads = [
            threading.Thread(target=self._sync_loop, name="live-sync", daemon=True),
            threading.Thread(target=self._run, name="live", daemon=True),
        ]
        for t in self._threads:
            t.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        """End the live loop: the sets being processed are finished, nothing else is; the stages are
        closed. Waits at most ``timeout_s`` (the sets being processed, then the stages' close)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for t in self._threads:
            t.join(timeout_s)

    # ------------------------------------------------------------------ sync thread
    def _sync_loop(self) -> None:
        every = self.cfg.live.every_n
        while not self.stopping:
            try:
                cam, frame = self.queue.get(timeout=SYNC_POLL_S)
            except queue.Empty:
                pass
            else:
                self.sync.push(cam, frame)
                while True:  # everything queued now, then the ready sets
                    try:
                        cam, frame = self.queue.get_nowait()
                    except queue.Empty:
                        break
                    self.sync.push(cam, frame)
            ready = self.sync.pop_ready(host_now_ns())
            self.stats.sets += len(ready)
            for fs in ready:
                if fs.index % every == 0:
                    self._offer(fs)
        with self._cond:
            self._cond.notify_all()

    def _offer(self, fs: FrameSet) -> None:
        with self._cond:
            held = self._slot
            if held is not None and held.complete and not fs.complete:
                self.stats.skipped += 1  # the newest complete set is kept; this incomplete one is dropped
                return
            if held is not None:
                self.stats.skipped += 1  # stale: a newer set is ready before it was taken
            self._slot = fs
            self._cond.notify_all()

    def _take(self) -> FrameSet | None:
        with self._cond:
            while self._slot is None and not self.stopping:
                self._cond.wait(SYNC_POLL_S)
            if self.stopping:
                return None
            fs, self._slot = self._slot, None
            return fs

    # ------------------------------------------------------------------ live thread
    def _build_stages(self) -> None:
        t0 = time.perf_counter()
        stages, errors = self._build(self.cfg, self.layout)
        self.stats.errors.update(errors)
        self.stats.stage_ms = {k: 0.0 for k in stages}
        self.stages = stages
        self.stages_ready_ns = host_now_ns()
        log.info("live: stages %s ready in %.2f s", ", ".join(stages) or "(none)", time.perf_counter() - t0)

    def _run(self) -> None:
        if self._build is not None:
            try:
                self._build_stages()
            except Exception as e:  # noqa: BLE001 - said like a stage that cannot be built
                log.exception("live: building the stages failed")
                self.stats.errors["build"] = f"{type(e).__name__}: {e}"
        if self.pipelined and len(self.stages) > 1:
            self._run_pipelined()
        else:
            while True:
                fs = self._take()
                if fs is None:
                    break
                self.process(fs)
        self.stopped_ns = host_now_ns()
        with self._cond:  # a set ready at the stop is not processed: dropped, counted
            if self._slot is not None:
                self.stats.skipped += 1
                self._slot = None
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
        self.ended_ns = host_now_ns()

    def _run_pipelined(self) -> None:
        """The first stage (the 2D) of the next set on this thread while the others (triangulation,
        tracking, the outputs) finish the last one on ``live-3d``: the sets stay in order for the tracker,
        one set is handed over at a time (the 2D waits when the 3D is behind), and the cores do not idle
        while the 3D runs."""
        handoff: queue.Queue = queue.Queue(maxsize=1)

        def back() -> None:
            while (step := handoff.get()) is not None:
                self._back(step)

        t = threading.Thread(target=back, name="live-3d", daemon=True)
        t.start()
        try:
            while (fs := self._take()) is not None:
                # a set whose 2D is done goes through the 3D even after a stop: the 3D costs a few ms and
                # the 3D thread is at most one set behind
                handoff.put(self._front(fs))
        finally:
            handoff.put(None)
            t.join()

    def process(self, fs: FrameSet, final: bool = False) -> LiveStep:
        """Run the stages on ``fs``, count it, hand it to ``on_step``."""
        return self._back(self._front(fs, final))

    def _stage(self, name: str, stage: Stage, step: LiveStep) -> None:
        t0 = time.perf_counter()
        try:
            stage(step)
        except Exception as e:
            if name not in self.stats.errors:
                log.exception("live: stage %r failed", name)
            self.stats.errors[name] = f"{type(e).__name__}: {e}"
        self.stats.stage_ms[name] = self.stats.stage_ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def _front(self, fs: FrameSet, final: bool = False) -> LiveStep:
        """A step for ``fs`` through the first stage."""
        step = LiveStep(fs, self.cfg.names, {"final": final})
        for name, stage in list(self.stages.items())[:1]:
            self._stage(name, stage, step)
        return step

    def _back(self, step: LiveStep) -> LiveStep:
        """The other stages, then the step counted and handed to ``on_step``."""
        for name, stage in list(self.stages.items())[1:]:
            self._stage(name, stage, step)
        fs = step.frameset
        newest = max(f.t_host_ns for f in fs.frames.values() if f is not None)
        self.stats.latency_ms.append((host_now_ns() - newest) / 1e6)
        self.stats.processed += 1
        self.stats.complete += fs.complete
        if step.outputs.get("jump"):
            self.stats.jumps.append(step.outputs["jump"])
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
            "jumps": list(self.stats.jumps),
        }

    def summary_line(self) -> str:
        s = self.summary()
        stages = ", ".join(f"{k} {v:.1f} ms" for k, v in s["stage_ms_mean"].items()) or "no stages"
        return (
            f"{s['processed']} frame sets processed ({s['skipped']} stale ones dropped, {s['complete']} "
            "complete), "
            f"latency median {s['latency_ms_median']:.1f} ms, p95 {s['latency_ms_p95']:.1f} ms; {stages}"
            + jump_line(s["jumps"])
        ) + "".join(f"; {r()}" for r in self.reports)


def jump_line(jumps: list[dict]) -> str:
    """``"; the clock jumped N times (...)"`` for the live summary and page, ``""`` without jumps.

    >>> jump_line([{"frame_set": 7, "t_ns_before": 2_500_000_000, "t_ns_after": 0, "why": "time went back"}])
    '; the clock jumped 1 time (before frame set 7: time went back, -2.500 s): a new track segment'
    """
    if not jumps:
        return ""
    j = jumps[-1]
    n = len(jumps)
    last = "" if n == 1 else "last "
    return (
        f"; the clock jumped {n} time{'s' if n > 1 else ''} ({last}before frame set {j['frame_set']}: "
        f"{j['why']}, {(j['t_ns_after'] - j['t_ns_before']) / 1e9:+.3f} s): a new track segment"
        + (" each" if n > 1 else "")
    )
