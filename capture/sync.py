"""Grouping frames of all cameras into frame sets, and the timing report (fps, drops, skew, drift).

Pure functions over timestamp arrays (``group_timestamps``, ``timing_report``) and a thin online
class (``Synchroniser``) that the live path feeds frame by frame; a test checks they agree.

A frame set holds at most one frame per camera whose timestamps all lie within ``tolerance_ns``
(default half a frame period) of the set's first frame.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from roomcap.capture.sources import Frame

log = logging.getLogger(__name__)


def group_timestamps(t_ns: dict[str, np.ndarray], tolerance_ns: int) -> np.ndarray:
    """Match frames across cameras. t_ns: camera -> (T_c,) increasing int64.

    Returns (S, C) int64 frame indices (columns in dict order), -1 where a camera has no frame in
    the set. A sweep over all timestamps in time order: a set opens at the earliest unassigned
    frame and takes, per camera, the first frame within ``tolerance_ns`` of it.
    """
    names = list(t_ns)
    C = len(names)
    ts = [np.asarray(t_ns[n], np.int64).reshape(-1) for n in names]
    ptr = [0] * C
    sets = []
    while True:
        heads = [ts[c][ptr[c]] if ptr[c] < len(ts[c]) else None for c in range(C)]
        live = [h for h in heads if h is not None]
        if not live:
            break
        t0 = min(live)
        row = [-1] * C
        for c, h in enumerate(heads):
            if h is not None and h - t0 <= tolerance_ns:
                row[c] = ptr[c]
                ptr[c] += 1
        sets.append(row)
    return np.asarray(sets, np.int64).reshape(-1, C)


def _drift_ppm(t_dev_ns: np.ndarray, t_host_ns: np.ndarray) -> float:
    """Rate of the device clock against the host clock, in ppm (robust line fit on arrival times)."""
    if len(t_dev_ns) < 10:
        return float("nan")
    x = (t_host_ns - t_host_ns[0]).astype(np.float64)
    y = (t_dev_ns - t_dev_ns[0]).astype(np.float64) - x
    if x[-1] - x[0] < 1e9:  # under a second: nothing to say about drift
        return float("nan")
    # arrival jitter is one-sided (late frames), so fit the lower envelope: per-window minima
    nwin = int(min(50, max(5, len(x) // 20)))
    edges = np.linspace(x[0], x[-1] + 1, nwin + 1)
    xs, ys = [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        m = (x >= a) & (x < b)
        if m.any():
            i = np.argmax(np.where(m, y, -np.inf))  # device - host largest = host stamp least delayed
            xs.append(x[i])
            ys.append(y[i])
    slope = np.polyfit(np.asarray(xs), np.asarray(ys), 1)[0]
    return float(slope * 1e6)


def timing_report(
    tables: dict[str, np.ndarray],
    nominal_fps: dict[str, float] | None = None,
    tolerance_ns: int | None = None,
) -> dict:
    """Per-camera fps, drops, drift and cross-camera skew from frames.csv tables.

    tables: camera -> (T,4) int64 [frame_index, t_ns, t_host_ns, sequence].
    Returns {"cameras": {cam: {...}}, "skew_ms_median", "skew_ms_p95", "sets", "complete_sets"}.
    """
    cams: dict[str, dict] = {}
    for name, tab in tables.items():
        tab = np.asarray(tab, np.int64).reshape(-1, 4)
        d: dict = {"frames": int(len(tab))}
        if len(tab) >= 2:
            dt = np.diff(tab[:, 1])
            span_s = (tab[-1, 1] - tab[0, 1]) / 1e9
            d["fps_measured"] = float((len(tab) - 1) / span_s) if span_s > 0 else float("nan")
            d["frame_interval_ms_median"] = float(np.median(dt) / 1e6)
            seq_gaps = np.diff(tab[:, 3]) - 1
            d["dropped_sequence"] = int(np.clip(seq_gaps, 0, None).sum())
            d["latency_ms_median"] = float(np.median(tab[:, 2] - tab[:, 1]) / 1e6)
            d["drift_ppm"] = _drift_ppm(tab[:, 1], tab[:, 2])
        cams[name] = d
    out: dict = {"cameras": cams}
    if len(tables) >= 2 and all(len(t) for t in tables.values()):
        if tolerance_ns is None:
            fps = [v for v in (nominal_fps or {}).values() if v] or [
                c.get("fps_measured", 30.0) for c in cams.values()
            ]
            tolerance_ns = int(0.5e9 / max(fps))
        sets = group_timestamps({k: np.asarray(v)[:, 1] for k, v in tables.items()}, tolerance_ns)
        complete = (sets >= 0).all(axis=1)
        out["sets"] = int(len(sets))
        out["complete_sets"] = int(complete.sum())
        out["tolerance_ms"] = tolerance_ns / 1e6
        if complete.any():
            t = np.stack([np.asarray(tables[k])[sets[complete, c], 1] for c, k in enumerate(tables)], axis=1)
            skew = (t.max(axis=1) - t.min(axis=1)) / 1e6
            out["skew_ms_median"] = float(np.median(skew))
            out["skew_ms_p95"] = float(np.percentile(skew, 95))
            out["skew_ms_max"] = float(skew.max())
    return out


@dataclass
class FrameSet:
    index: int
    t_ns: int  # median of the member timestamps
    frames: dict[str, Frame | None]  # every camera, None where missing

    @property
    def complete(self) -> bool:
        return all(f is not None for f in self.frames.values())

    @property
    def loops(self) -> int:
        """The most times a member's source started again from its beginning (``Frame.loops``)."""
        return max((f.loops for f in self.frames.values() if f is not None), default=0)

    @property
    def skew_ns(self) -> int:
        t = [f.t_ns for f in self.frames.values() if f is not None]
        return max(t) - min(t) if t else 0


@dataclass
class SyncStats:
    sets: int = 0
    complete: int = 0
    unmatched: dict[str, int] = field(default_factory=dict)  # frames that joined no set
    skew_ns_max: int = 0


class Synchroniser:
    """Online grouping: ``push(cam, frame)``, then ``pop_ready(now_ns)`` returns the finished sets.

    A set is emitted when every camera has a frame within tolerance of the earliest buffered
    frame, or incomplete once that frame has waited ``max_wait_ns`` of host time (a camera is
    late or gone). Frames older than a newer complete set are dropped as unmatched.
    """

    def __init__(self, names: list[str] | tuple[str, ...], tolerance_ns: int, max_wait_ns: int = 200_000_000):
        self.names = list(names)
        self.tol = int(tolerance_ns)
        self.max_wait = int(max_wait_ns)
        self.buf: dict[str, deque[Frame]] = {n: deque() for n in self.names}
        self.stats = SyncStats(unmatched={n: 0 for n in self.names})
        self.ended: set[str] = set()
        self._index = 0

    def push(self, cam: str, frame: Frame | None) -> None:
        if frame is None:
            self.ended.add(cam)
        else:
            self.buf[cam].append(frame)

    def _emit(self, t0: int) -> FrameSet:
        frames: dict[str, Frame | None] = {}
        for n in self.names:
            b = self.buf[n]
            frames[n] = b.popleft() if b and b[0].t_ns - t0 <= self.tol else None
        ts = sorted(f.t_ns for f in frames.values() if f is not None)
        fs = FrameSet(self._index, ts[len(ts) // 2], frames)
        self._index += 1
        self.stats.sets += 1
        self.stats.complete += fs.complete
        self.stats.skew_ns_max = max(self.stats.skew_ns_max, fs.skew_ns)
        return fs

    def pop_ready(self, now_host_ns: int, flush: bool = False) -> list[FrameSet]:
        out = []
        while True:
            heads = {n: b[0] for n, b in self.buf.items() if b}
            if not heads:
                break
            t0 = min(f.t_ns for f in heads.values())
            waiting = [n for n in self.names if n not in heads and n not in self.ended]
            # a camera whose head is already past t0 + tol cannot contribute: it is not "waiting"
            if not waiting:
                out.append(self._emit(t0))
                continue
            oldest = min(heads.values(), key=lambda f: f.t_ns)
            if flush or now_host_ns - oldest.t_host_ns > self.max_wait:
                out.append(self._emit(t0))
                continue
            break
        return out
