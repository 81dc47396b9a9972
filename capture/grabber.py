"""One grabbing thread per camera: reads its FrameSource, fans frames out to bounded queues.

A full queue never blocks the camera: the frame is dropped for that consumer and counted. A live
source that disconnects is reopened with exponential backoff; the gap (last frame before, first
frame after) is recorded. A file source ends the thread at its end.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field

from roomcap.capture.sources import (
    Frame,
    FrameSource,
    SourceDisconnected,
    SourceError,
    SourceInfo,
    host_now_ns,
)

log = logging.getLogger(__name__)

END = None  # sentinel put into every queue when the grabber ends


@dataclass
class Gap:
    """A disconnect: no frames between ``after_t_ns`` (last before) and ``before_t_ns`` (first after)."""

    after_t_ns: int
    before_t_ns: int | None = None  # None while still disconnected / never came back
    after_sequence: int | None = None
    before_sequence: int | None = None
    attempts: int = 0
    reason: str = ""

    @property
    def duration_s(self) -> float | None:
        return None if self.before_t_ns is None else (self.before_t_ns - self.after_t_ns) / 1e9

    def to_dict(self) -> dict:
        d = {
            "after_t_ns": self.after_t_ns,
            "before_t_ns": self.before_t_ns,
            "after_sequence": self.after_sequence,
            "before_sequence": self.before_sequence,
            "attempts": self.attempts,
            "reason": self.reason,
            "duration_s": self.duration_s,
        }
        return {k: v for k, v in d.items() if v is not None}


@dataclass
class GrabStats:
    frames: int = 0
    dropped_queue: dict[str, int] = field(default_factory=dict)  # consumer -> frames dropped (queue full)
    dropped_source: int = 0  # gaps in the source's own sequence numbers (outside disconnects)
    gaps: list[Gap] = field(default_factory=list)
    ended: str = ""  # why the thread ended: "eof", "stopped", "gave up", "error: ..."
    # stretches with no frame from a source that neither ended nor failed (capture.recorder's watchdog):
    # {"after_t_ns": the last frame's time, "seconds": how long (so far, while it lasts)}
    stalls: list[dict] = field(default_factory=list)


class Grabber(threading.Thread):
    """Owns one opened source; ``sinks`` maps a consumer name to its bounded queue."""

    def __init__(
        self,
        name: str,
        source: FrameSource,
        info: SourceInfo,
        sinks: dict[str, queue.Queue],
        stop: threading.Event,
        reconnect_initial_s: float = 0.1,
        reconnect_max_s: float = 2.0,
        give_up_s: float = 60.0,
        on_gap=None,
    ):
        super().__init__(name=f"grab-{name}", daemon=True)
        self.cam = name
        self.source = source
        self.info = info
        self.sinks = sinks
        self.stop_event = stop
        self.reconnect_initial_s = reconnect_initial_s
        self.reconnect_max_s = reconnect_max_s
        self.give_up_s = give_up_s
        self.on_gap = on_gap
        self.stats = GrabStats(dropped_queue={k: 0 for k in sinks})
        self.last: Frame | None = None
        self.last_mono = time.monotonic()  # when the last frame came (or the thread started)
        self.stalled: dict | None = None  # the open stall (an entry of stats.stalls), set by check_stall

    def _push(self, frame: Frame | None) -> None:
        wait = self.source.waits_for_consumers
        for key, q in self.sinks.items():
            try:
                q.put_nowait(frame)
            except queue.Full:
                if frame is END:
                    q.put(END)  # the end marker must arrive; consumers are draining
                elif wait and key == "writer":
                    # a file that must be recorded whole: wait for the writer (not for live processing)
                    while not self.stop_event.is_set():
                        try:
                            q.put(frame, timeout=0.1)
                            break
                        except queue.Full:
                            continue
                    else:
                        self.stats.dropped_queue[key] += 1
                else:
                    self.stats.dropped_queue[key] += 1

    def _reconnect(self, reason: str) -> bool:
        last = self.last
        gap = Gap(
            after_t_ns=last.t_ns if last else host_now_ns(),
            after_sequence=last.sequence if last else None,
            reason=reason,
        )
        self.stats.gaps.append(gap)
        log.warning("%s: disconnected (%s); reconnecting", self.cam, reason)
        if self.on_gap:
            self.on_gap(self.cam, gap)
        self.source.close()
        delay = self.reconnect_initial_s
        t_start = time.monotonic()
        while not self.stop_event.is_set():
            if self.give_up_s and time.monotonic() - t_start > self.give_up_s:
                log.error("%s: gave up reconnecting after %.0f s", self.cam, self.give_up_s)
                return False
            gap.attempts += 1
            try:
                self.info = self.source.open()
                log.info("%s: reconnected after %d attempt(s)", self.cam, gap.attempts)
                return True
            except SourceError as e:
                log.debug("%s: reconnect attempt %d failed: %s", self.cam, gap.attempts, e)
            self.stop_event.wait(delay)
            delay = min(delay * 2, self.reconnect_max_s)
        return False

    def check_stall(self, after_s: float) -> None:
        """Called by the recorder's watchdog: a source that gave no frame for ``after_s`` and neither ended
        nor failed (a read that blocks: a camera that stopped sending) is reported, once per stall, and its
        length kept up to date; the other cameras go on (each has its own thread, the synchroniser emits
        incomplete frame sets)."""
        quiet = time.monotonic() - self.last_mono
        if self.stalled is not None:
            self.stalled["seconds"] = round(quiet, 3)
        elif quiet >= after_s and self.is_alive() and not self.stop_event.is_set():
            self.stalled = {"after_t_ns": self.last.t_ns if self.last else None, "seconds": round(quiet, 3)}
            self.stats.stalls.append(self.stalled)
            log.warning(
                "%s: no frame for %.1f s (the source stalls); the other cameras go on", self.cam, quiet
            )

    def run(self) -> None:
        pending_gap: Gap | None = None
        try:
            while not self.stop_event.is_set():
                try:
                    frame = self.source.read()
                except SourceDisconnected as e:
                    if not self.source.live:
                        self.stats.ended = f"error: {e}"
                        break
                    if not self._reconnect(str(e)):
                        self.stats.ended = "stopped" if self.stop_event.is_set() else "gave up"
                        break
                    pending_gap = self.stats.gaps[-1]
                    continue
                if frame is None:
                    self.stats.ended = "eof"
                    break
                if pending_gap is not None:
                    pending_gap.before_t_ns = frame.t_ns
                    pending_gap.before_sequence = frame.sequence
                    if self.on_gap:
                        self.on_gap(self.cam, pending_gap)
                    pending_gap = None
                elif self.last is not None and frame.sequence > self.last.sequence + 1:
                    self.stats.dropped_source += frame.sequence - self.last.sequence - 1
                self.last = frame
                self.last_mono = time.monotonic()
                if self.stalled is not None:
                    log.warning(
                        "%s: frames again after %.1f s without one", self.cam, self.stalled["seconds"]
                    )
                    self.stalled = None
                self.stats.frames += 1
                self._push(frame)
            else:
                self.stats.ended = "stopped"
        except Exception as e:  # a source bug must not kill the session silently: record and end this camera
            log.exception("%s: grabber failed", self.cam)
            self.stats.ended = f"error: {type(e).__name__}: {e}"
        finally:
            try:
                self.source.close()
            finally:
                self._push(END)
