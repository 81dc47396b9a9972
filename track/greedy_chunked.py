"""The greedy tracker (:mod:`roomcap.track.greedy`) in bounded memory, chunk by chunk.

Two passes over the per-frame poses, each reading them in time chunks:

1. **Linking** (:class:`StreamLinker`): the frame-by-frame Hungarian pass of
   :func:`~roomcap.track.greedy.associate_mirrored` (:class:`~roomcap.track.greedy.FrameLinker`), keeping
   only the tracks still alive (seen within ``max_gap_s`` on the tracks' clock), plus, for the seam
   stitching of
   :func:`~roomcap.track.greedy.stitch_tracks`, each track's held last pose and its first ``max_gap_s``
   of poses; a track's stitch candidates are computed the moment it can no longer continue, and the
   data are dropped once no later track can need them. What grows with the session is one small int
   per pose slot and frame (the labels) and a few numbers per track.
2. **Building** (:func:`build_window`): gap filling, kinematic fill and smoothing of
   :func:`~roomcap.track.greedy.build_tracks` on each chunk plus a margin on either side
   (:func:`build_margin_s`: every filled or smoothed value depends on the poses within that many
   seconds); only the chunk's own frames are kept.

The result equals :func:`~roomcap.track.greedy.track_poses` on the whole session (bit for bit: the same
operations in the same order on the same samples; the smoothing adds zero-weight terms where a window
is shorter, which changes no value), whatever the chunk length.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from roomcap.track.greedy import (
    FrameLinker,
    TrackerConfig,
    build_tracks,
    long_enough,
    nominal_dt,
    pause_clock,
    pose_distance,
    segment_frames,
)


class StreamLinker(FrameLinker):
    """The linking pass of the greedy tracker (:class:`~roomcap.track.greedy.FrameLinker`), fed frame by
    frame (:meth:`step`) or by chunks (:meth:`run`), keeping what the seam stitching of
    :func:`~roomcap.track.greedy.stitch_tracks` needs.

    ``clock (T,)`` and ``pauses (T,)`` of the whole session (:func:`~roomcap.track.greedy.pause_clock`;
    small). Labels are the raw track numbers of the pass (by first appearance); :meth:`finish` returns
    the label -> final track id map after stitching and the ``min_track_frames`` filter (-1 = dropped).
    """

    def __init__(self, *args, **kwargs) -> None:  # FrameLinker's arguments
        super().__init__(*args, **kwargs)
        # per track, for stitching and the filter (a few numbers per track)
        self.first: list[int] = []
        self.last: list[int] = []
        self.count: list[int] = []
        self.room: list[int] = []  # the longest stretch without a pause among the track's frames
        self.stretch = segment_frames(self.pauses)
        self.end: dict[int, np.ndarray] = {}  # held last raw pose (joints from earlier frames)
        self.head: dict[int, list[tuple[int, np.ndarray]]] = {}  # rows within window of the first
        self.cands: list[tuple[float, int, int]] = []

    def _retired(self, k: int) -> None:
        if self.cfg.stitch:
            self._candidates(k)
        self.end.pop(k, None)

    def retire(self, now: float, final: bool = False) -> None:
        super().retire(now, final)
        if not final:  # heads no track still to retire can need
            for b in [b for b in self.head if self.clock[self.first[b]] + 2 * self.window < now]:
                del self.head[b]

    def _candidates(self, a: int) -> None:
        """:func:`~roomcap.track.greedy.stitch_tracks`'s candidate links of track ``a``."""
        cfg, la = self.cfg, self.last[a]
        end = self.end[a]
        for b in sorted(self.head):
            fb = self.first[b]
            if not (fb > la and self.clock[fb] - self.clock[la] <= self.window):
                continue
            ts = np.asarray([t for t, _ in self.head[b]])
            since = self.clock[ts] - self.clock[la]
            sel = since <= self.window
            if not sel.any():
                continue
            X = np.stack([x for (_, x), s in zip(self.head[b], sel, strict=True) if s])
            ts, since = ts[sel], since[sel]
            d = pose_distance(end[None], X)[0]
            limit = cfg.tau_m + cfg.max_speed_m_s * np.clip(since - 1.0 / self.fps, 0.0, cfg.max_gap_s)
            limit = limit + cfg.pause_gate_m * (self.pauses[ts] > self.pauses[la])
            hit = np.flatnonzero(d < limit)
            if len(hit):
                self.cands.append((float(d[hit[0]]), a, int(b)))

    def _joined(self, k: int, t: int, raw: np.ndarray, born: bool) -> None:
        """Stitch bookkeeping of a pose (mirror-corrected raw pose) joining track k at frame t."""
        if born:
            self.first.append(t)
            self.last.append(t)
            self.count.append(0)
            self.room.append(0)
            self.head[k] = []
        self.last[k] = t
        self.count[k] += 1
        self.room[k] = max(self.room[k], int(self.stretch[t]))
        if self.cfg.stitch:
            e = self.end.get(k)
            held = raw.copy()
            if e is not None:
                miss = ~np.isfinite(held).all(-1)
                held[miss] = e[miss]
            self.end[k] = held
            h = self.head.get(k)
            if h is not None and self.clock[t] - self.clock[self.first[k]] <= self.window:
                h.append((t, raw.copy()))

    def run(self, t0: int, xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames t0 .. t0+len-1: labels (n,P), mirrored (n,P)."""
        n, P = xyz_m.shape[:2]
        lab = np.full((n, P), -1, np.int64)
        mir = np.zeros((n, P), bool)
        for i in range(n):
            lab[i], mir[i] = self.step(t0 + i, xyz_m[i])
        return lab, mir

    def finish(self) -> np.ndarray:
        """(K,) final track id of each label (stitched chains share one; -1 = dropped by the filter)."""
        self.retire(np.inf, final=True)
        self.head.clear()
        K = self.n_tracks
        succ, pred = np.full(K, -1), np.full(K, -1)
        for _, a, b in sorted(self.cands):
            if succ[a] < 0 and pred[b] < 0:
                succ[a], pred[b] = b, a
        root = np.arange(K)
        first = np.asarray(self.first, np.int64)
        for k in np.argsort(first, kind="stable"):
            if pred[k] >= 0:
                root[k] = root[pred[k]]
        frames = np.bincount(root, weights=np.asarray(self.count, np.float64), minlength=K)
        room = np.zeros(K, np.int64)
        np.maximum.at(room, root, np.asarray(self.room, np.int64))
        kept = np.flatnonzero(long_enough(frames, room, self.cfg.min_track_frames))
        final = np.full(K, -1, np.int64)
        final_of_root = np.full(K, -1, np.int64)
        final_of_root[kept] = np.arange(len(kept))
        final[:] = final_of_root[root] if K else final
        return final


def skeleton_depth(parents: np.ndarray) -> int:
    """Edges on the longest path from a root (the chain length of the kinematic fill)."""
    depth = 0
    for j in range(len(parents)):
        d, p = 0, int(parents[j])
        while p >= 0 and d <= len(parents):
            d, p = d + 1, int(parents[p])
        depth = max(depth, d)
    return depth


def build_margin_s(cfg: TrackerConfig, fps: float, parents: np.ndarray | None) -> float:
    """Seconds of poses on either side of a frame that its built value depends on: the interpolation
    (``max_gap_s``), then each level of the kinematic fill (``occlusion_fill_s``), then the smoothing
    (3 sigma), each plus a frame."""
    dt = nominal_dt(fps)
    m = cfg.max_gap_s + dt
    if cfg.occlusion_fill_s > 0 and parents is not None:
        m += skeleton_depth(parents) * (cfg.occlusion_fill_s + dt)
    if cfg.sigma_s:
        m += int(3.0 * cfg.sigma_s * fps + 0.5) / fps + dt
    return m + 2 * dt


@dataclass(frozen=True)
class BuiltChunk:
    """Tracks of frames [a, b): ids (K,), xyz (n,K,J,3), confidence, std, flags (n,K,J)."""

    a: int
    b: int
    track_id: np.ndarray
    xyz_m: np.ndarray
    confidence: np.ndarray
    std_m: np.ndarray
    flags: np.ndarray


def build_window(
    xyz_m: np.ndarray,
    labels: np.ndarray,
    mirrored: np.ndarray,
    final: np.ndarray,
    confidence: np.ndarray | None,
    std_m: np.ndarray | None,
    cfg: TrackerConfig,
    parents: np.ndarray | None,
    flip: np.ndarray | None,
    fps: float,
    t_s: np.ndarray,
    core: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`~roomcap.track.greedy.build_tracks` on a window (n frames: the chunk and its margins) with
    the final track ids; returns the arrays of the ``core`` frames (window positions) and only the tracks
    with anything there: ids (K,), xyz (m,K,J,3), confidence, std, flags."""
    assign = np.where(labels >= 0, final[np.maximum(labels, 0)], -1)
    ids, X, Cf, S, Fl = build_tracks(
        xyz_m,
        assign,
        confidence,
        std_m,
        replace(cfg, min_track_frames=1),  # the filter was applied on the whole tracks (final)
        parents,
        mirrored,
        flip,
        fps=fps,
        t_s=t_s,
    )
    a, b = core
    X, Cf, S, Fl = X[a:b], Cf[a:b], S[a:b], Fl[a:b]
    has = (
        np.isfinite(X).any((0, 2, 3))
        | np.isfinite(S).any((0, 2))
        | (Cf != 0).any((0, 2))
        | (Fl != 0).any((0, 2))
        | np.isin(ids, assign[a:b])
    )
    return ids[has], X[:, has], Cf[:, has], S[:, has], Fl[:, has]


def window_bounds(t_s: np.ndarray, a: int, b: int, margin_s: float) -> tuple[int, int]:
    """Positions [w0, w1) of the frames within ``margin_s`` of chunk [a, b)."""
    w0 = int(np.searchsorted(t_s, t_s[a] - margin_s, side="left"))
    w1 = int(np.searchsorted(t_s, t_s[b - 1] + margin_s, side="right"))
    return w0, w1


PoseReader = Callable[[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""(a, b) -> xyz_m (b-a,P,J,3), confidence (b-a,P,J), std_m (b-a,P,J) of frames [a, b) (P may vary)."""


def link_chunks(
    read: PoseReader,
    chunks: list[tuple[int, int]],
    cfg: TrackerConfig,
    fps: float,
    flip: np.ndarray | None,
    t_s: np.ndarray,
    facing: tuple[int, int, int] | None,
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Pass 1 over the chunks: per chunk labels (n,P) int32 and mirrored (n,P), and the final id map
    (``facing``: :func:`~roomcap.track.greedy.associate_mirrored`'s)."""
    clock, pauses = pause_clock(t_s, cfg.max_gap_s, fps)
    linker = StreamLinker(cfg, fps, flip, clock, pauses, facing)
    labels, mirrored = [], []
    for a, b in chunks:
        xyz, _, _ = read(a, b)
        lab, mir = linker.run(a, np.asarray(xyz, np.float64))
        labels.append(lab.astype(np.int32))
        mirrored.append(mir)
    return labels, mirrored, linker.finish()


def _gather(parts: list[np.ndarray], chunks: list[tuple[int, int]], w0: int, w1: int, fill) -> np.ndarray:
    """Rows [w0, w1) of per-chunk arrays (n_i,P_i,...) padded to the widest P."""
    sel = [(p, a, b) for p, (a, b) in zip(parts, chunks, strict=True) if b > w0 and a < w1]
    P = max(p.shape[1] for p, _, _ in sel)
    out = []
    for p, a, b in sel:
        piece = p[max(w0 - a, 0) : min(w1, b) - a]
        w = [(0, 0)] * piece.ndim
        w[1] = (0, P - piece.shape[1])
        out.append(np.pad(piece, w, constant_values=fill))
    return np.concatenate(out)


def build_chunks(
    read: PoseReader,
    chunks: list[tuple[int, int]],
    labels: list[np.ndarray],
    mirrored: list[np.ndarray],
    final: np.ndarray,
    cfg: TrackerConfig,
    parents: np.ndarray | None,
    flip: np.ndarray | None,
    fps: float,
    t_s: np.ndarray,
    todo: set[int] | None = None,
) -> Iterator[tuple[int, BuiltChunk]]:
    """Pass 2: yield (chunk number, :class:`BuiltChunk`) for the chunks in ``todo`` (default all)."""
    margin = build_margin_s(cfg, fps, parents)
    for i, (a, b) in enumerate(chunks):
        if todo is not None and i not in todo:
            continue
        w0, w1 = window_bounds(t_s, a, b, margin)
        xyz, conf, std = read(w0, w1)
        lab = _gather(labels, chunks, w0, w1, -1)
        mir = _gather(mirrored, chunks, w0, w1, False)
        P = max(xyz.shape[1], lab.shape[1])
        xyz = _pad_p(np.asarray(xyz, np.float64), P, np.nan)
        conf = _pad_p(np.asarray(conf, np.float64), P, 0.0)
        std = _pad_p(np.asarray(std, np.float64), P, np.nan)
        lab = _pad_p(lab, P, -1)
        mir = _pad_p(mir, P, False)
        ids, X, Cf, S, Fl = build_window(
            xyz, lab, mir, final, conf, std, cfg, parents, flip, fps, t_s[w0:w1], (a - w0, b - w0)
        )
        yield i, BuiltChunk(a, b, ids, X, Cf, S, Fl)


def _pad_p(x: np.ndarray, P: int, fill) -> np.ndarray:
    if x.shape[1] == P:
        return x
    w = [(0, 0)] * x.ndim
    w[1] = (0, P - x.shape[1])
    return np.pad(x, w, constant_values=fill)
