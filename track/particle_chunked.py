"""The particle tracker (:mod:`roomcap.track.particle`) in time chunks with bounded memory.

Two passes, each writing a folder of parts (:class:`roomcap.triangulate.chunks.PartStore`: every part written
atomically and entered in an index with its size and sha256; a part that is missing, truncated or
changed is rebuilt, never trusted):

1. **Filtering** (``track/particle_raw.parts/``): the detections are read chunk by chunk
   (:meth:`roomcap.triangulate.stage.DetectionPlan.chunk`) and the recursive filter steps over them. Each part
   holds the chunk's raw per-frame estimates (:class:`roomcap.track.particle.RawEstimates`: the tracks
   present, their positions, spread, confidence, flags, views and evidence) and the filter's state after the
   chunk's last frame (:meth:`~roomcap.track.particle.ParticleTracker.state_arrays`: samples, motion state,
   lost identities, the clock, the random generator). A killed run resumes at the first part that is not
   valid, from the state in the part before it, and continues bit for bit.
2. **Clean-up** (``track/tracks.parts/``, one ``tracks/1`` file per chunk, read by
   :meth:`roomcap.track.trackfile.TrackFile.load` as one file): :func:`roomcap.track.particle.finish_tracks`
   on each
   chunk plus a margin on either side (:func:`finish_margin_s`: ``end_after_s`` + the smoothing radius on
   the tracks' clock), with each track's evidence counted over the whole session for ``min_track_s``; only
   the chunk's own frames are kept.

The result equals :func:`roomcap.track.particle.track_sequence` on the whole session bit for bit: the filter
runs the same steps on the same detections (the state is restored exactly), and each cleaned frame
depends only on the raw estimates within the margin (the smoothing adds zero-weight terms where a window
is shorter, which changes no value). Memory: one chunk of detections and raw estimates, the filter's
state (one (N,J,3) sample set and motion state per live track), and per frame of the session a few
numbers (times); the heap's free pages are returned to the OS every second of frames
(:func:`roomcap.core.memory.release_free_memory`: without it glibc's fragmented heap grew a 1-minute
12-camera session's process to 1.6 GB for 0.5 GB of live data). Confidence maps (``use_maps``) are
read whole by :func:`roomcap.track.stage.load_maps`, so a session with maps is not bounded by the chunk.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.core.fileio import save_npz
from roomcap.core.memory import TRIM_EVERY, release_free_memory
from roomcap.core.progress import Progress
from roomcap.track.greedy import frame_times_s, long_enough, nominal_dt, pause_clock, segment_frames
from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_io import focal_lengths, load_maps, source_of, track_arrays_to_file
from roomcap.track.particle_offline import (
    RawEstimates,
    check_times,
    finish_tracks,
    gather_estimates,
    min_evidence_frames,
    warn_sparse_time,
)
from roomcap.triangulate.chunks import NpzRows, PartStore, file_stamp, hash_key, parts_dir
from roomcap.triangulate.multiview import plan_detections, session_fps

log = logging.getLogger(__name__)

RAW_SCHEMA = "particle_raw/1"
_RAW_KEYS = ("track_id", "xyz_m", "std_m", "confidence", "flags", "n_views", "seen")


def raw_parts_dir(lay: SessionLayout) -> Path:
    """``track/particle_raw.parts``: pass 1's parts (raw estimates + filter state per chunk)."""
    return lay.tracks.parent / "particle_raw.parts"


def finish_margin_s(cfg: ParticleConfig, fps: float) -> float:
    """Seconds on the tracks' clock on either side of a frame that its cleaned value depends on: a track
    coasts at most ``end_after_s`` without evidence (the pause mask looks back that far, the coast trim
    forward), and the smoothing reaches its radius (3 sigma) beyond; plus a few frames."""
    dt = nominal_dt(fps)
    m = cfg.end_after_s + 2 * dt
    if cfg.smooth_sigma_s:
        m += int(3.0 * cfg.smooth_sigma_s * fps + 0.5) / fps + dt
    return m + 2 * dt


def window_bounds(clock: np.ndarray, a: int, b: int, margin_s: float) -> tuple[int, int]:
    """Positions [w0, w1) of the frames within ``margin_s`` (on the tracks' clock) of chunk [a, b)."""
    w0 = int(np.searchsorted(clock, clock[a] - margin_s, side="left"))
    w1 = int(np.searchsorted(clock, clock[b - 1] + margin_s, side="right"))
    return w0, w1


class RawReader:
    """Frames [a, b) of pass 1's raw estimates on one grid of the ids present (the parts a range touches,
    the last few kept in memory)."""

    def __init__(self, store: PartStore, chunks: list[tuple[int, int]], J: int) -> None:
        self.store, self.chunks, self.J = store, chunks, J
        self._cache: dict[int, dict[str, np.ndarray]] = {}

    def _part(self, i: int) -> dict[str, np.ndarray]:
        if i not in self._cache:
            if len(self._cache) >= 3:
                self._cache.pop(next(iter(self._cache)))
            with NpzRows(self.store.part_path(i)) as r:
                self._cache[i] = {k: r.full(k) for k in _RAW_KEYS}
        return self._cache[i]

    def evidence(self, run: np.ndarray) -> tuple[dict[int, int], dict[int, int]]:
        """Evidence frames of every id over the whole session, and the longest stretch without a pause
        among them (``run`` (T,): :func:`roomcap.track.greedy.segment_frames` of the session); reads only
        ids and evidence."""
        out: dict[int, int] = {}
        room: dict[int, int] = {}
        for i, (a, b) in enumerate(self.chunks):
            with NpzRows(self.store.part_path(i)) as r:
                ids, seen = r.full("track_id"), r.full("seen")
            longest = np.where(seen, run[a:b, None], 0).max(0, initial=0)
            for tid, n, m in zip(ids.tolist(), seen.sum(0).tolist(), longest.tolist(), strict=True):
                out[tid] = out.get(tid, 0) + int(n)
                room[tid] = max(room.get(tid, 0), int(m))
        return out, room

    def __call__(self, a: int, b: int) -> RawEstimates:
        sel = [(i, f0, f1) for i, (f0, f1) in enumerate(self.chunks) if f1 > a and f0 < b]
        parts = [(self._part(i), max(a - f0, 0), min(b, f1) - f0) for i, f0, f1 in sel]
        ids = np.unique(np.concatenate([np.zeros(0, np.int64)] + [p["track_id"] for p, _, _ in parts]))
        T, K, J = b - a, len(ids), self.J
        out = RawEstimates(
            ids,
            np.full((T, K, J, 3), np.nan, np.float32),
            np.full((T, K, J), np.nan, np.float32),
            np.zeros((T, K, J), np.float32),
            np.zeros((T, K, J), np.uint8),
            np.zeros((T, K, J), np.int16),
            np.zeros((T, K), bool),
        )
        t = 0
        for p, lo, hi in parts:
            k = np.searchsorted(ids, p["track_id"])
            sl = slice(t, t + hi - lo)
            for name in _RAW_KEYS[1:]:
                getattr(out, name)[sl, k] = p[name][lo:hi]
            t += hi - lo
        return out


def track_session_particle_chunked(
    lay: SessionLayout,
    rig,
    cfg: ParticleConfig,
    chunk_s: float,
    progress: Progress | None = None,
) -> Path:
    """The streamed particle track stage (see the module docstring); writes ``track/tracks.parts/``."""
    plan = plan_detections(lay, rig, stream=True)
    try:
        fps = session_fps(lay, plan.t_ns)
        frames, t_ns = plan.frames, plan.t_ns
        T = plan.n_frames
        check_times(frames, t_ns)
        t_s = frame_times_s(frames, t_ns, fps)
        warn_sparse_time(t_s, cfg.at_fps(fps), fps)
        step = max(int(round(chunk_s * fps)), 1)
        chunks = [(a, min(a + step, T)) for a in range(0, T, step)] or [(0, 0)]
        tracker = ParticleTracker(plan.rig.projection_matrices(), focal_lengths(plan.rig), fps, cfg)
        key = hash_key(
            [
                "particle",
                repr(tracker.config.result_settings()),
                rig.sha256(),
                [file_stamp(m.path) for m in plan.metas],
                lay.session_toml.read_bytes() if lay.session_toml.exists() else b"",
                step,
            ]
        )
        if lay.tracks.exists():
            lay.tracks.unlink()
        out_store = PartStore(parts_dir(lay.tracks), "tracks")
        out_todo = set(out_store.open(key, chunks, {"fps": fps, "n_frames": T}))
        if not out_todo:
            out_store.finish()
            log.info("particle tracker (streamed): all %d chunks already done", len(chunks))
            return lay.tracks
        raw_store = PartStore(raw_parts_dir(lay), RAW_SCHEMA)
        todo = set(raw_store.open(key, chunks, {"fps": fps, "n_frames": T}))
        if len(todo) < len(chunks):
            log.info(
                "particle tracker: resuming, %d of %d filter chunks already done",
                len(chunks) - len(todo),
                len(chunks),
            )
        maps_at = load_maps(lay, plan.rig, frames) if cfg.use_maps else None
        if maps_at is not None:
            log.warning(
                "particle tracker (streamed): the confidence maps are read whole; memory is not bounded "
                "by the chunk (use_maps = false to stream)"
            )
        _filter_pass(tracker, plan, chunks, todo, raw_store, t_s, maps_at, progress)
        raw_store.finish()
        release_free_memory()  # pass 1's fragmented heap, before pass 2 allocates its windows
        # pass 2: the offline clean-up per chunk with margins, each track's evidence over the session
        counts, rooms = _cleanup_pass(
            tracker, chunks, out_todo, raw_store, out_store, (frames, t_ns, t_s), fps, rig, cfg
        )
        ids = list(counts)
        n_tracks = int(
            long_enough(
                np.asarray([counts[k] for k in ids], np.int64),
                np.asarray([rooms[k] for k in ids], np.int64),
                min_evidence_frames(tracker.config, fps),
            ).sum()
        )
        out_store.finish({"n_tracks": int(n_tracks)})
        log.info(
            "particle tracker (streamed): %d chunks (%d written now), %d tracks over %d frames",
            len(chunks),
            len(out_todo),
            n_tracks,
            T,
        )
    finally:
        plan.close()
    return lay.tracks


def _filter_pass(tracker, plan, chunks, todo, raw_store, t_s, maps_at, progress) -> None:
    """Pass 1: the filter over the chunks ``todo``, each chunk's raw estimates and the filter's end state
    written as one raw part (a resumed run starts from the state after the last valid part)."""
    T, J = plan.n_frames, tracker.skeleton.n_joints
    held = -1  # the chunk whose end state the tracker holds (-1: the start of the session)
    for i, (a, b) in enumerate(chunks):
        if i not in todo:
            continue
        if held != i - 1:  # resume from the state after the previous (valid) part
            with NpzRows(raw_store.part_path(i - 1)) as r:
                tracker.load_state_arrays({n: r.full(n) for n in r.names if n not in _RAW_KEYS})
        mv = plan.chunk(a, b)
        kp = np.moveaxis(mv.xy_px, 0, 1).astype(np.float32)  # (n,C,P,J,2)
        sc = np.moveaxis(mv.score, 0, 1).astype(np.float32)
        del mv  # the float64 chunk: only its float32 copy is stepped
        per_frame = []
        for t in range(b - a):
            g = a + t
            per_frame.append(
                tracker.step(kp[t], sc[t], g, None if maps_at is None else maps_at(g), float(t_s[g]))
            )
            if progress is not None:
                progress("track", g + 1, T)
            if t % TRIM_EVERY == TRIM_EVERY - 1:  # bounded resident memory (core.memory)
                release_free_memory()
        raw = gather_estimates(per_frame, J)
        arrays = {"schema": np.asarray(RAW_SCHEMA), **{k: getattr(raw, k) for k in _RAW_KEYS}}
        # stored, not deflated: the filter's float noise compresses to 0.6 of its size at 5x the time
        save_npz(raw_store.part_path(i), {**arrays, **tracker.state_arrays()}, compress=False)
        raw_store.commit(i)
        held = i
        del kp, sc, per_frame, raw


def _cleanup_pass(tracker, chunks, out_todo, raw_store, out_store, times, fps, rig, cfg):
    """Pass 2: the offline clean-up of each chunk with margins of the raw parts around it, each track's
    evidence counted over the whole session; returns the evidence and room per track id."""
    frames, t_ns, t_s = times
    J = tracker.skeleton.n_joints
    read = RawReader(raw_store, chunks, J)
    clock, pauses = pause_clock(t_s, tracker.config.max_gap_s, fps)
    counts, rooms = read.evidence(segment_frames(pauses))
    margin = finish_margin_s(tracker.config, fps)
    source = source_of(cfg) + " (streamed)"
    for i, (a, b) in enumerate(chunks):
        if i not in out_todo:
            continue
        w0, w1 = window_bounds(clock, a, b, margin) if b > a else (a, b)
        raw = read(w0, w1)
        ev = np.asarray([counts.get(int(k), 0) for k in raw.track_id], np.int64)
        room = np.asarray([rooms.get(int(k), 0) for k in raw.track_id], np.int64)
        res = finish_tracks(raw, t_s[w0:w1], tracker.config, fps, evidence_frames=ev, room_frames=room)
        core = slice(a - w0, b - w0)
        X, S, Cf, Fl = res.xyz_m[core], res.std_m[core], res.confidence[core], res.flags[core]
        has = (np.isfinite(X).any((0, 2, 3)) | np.isfinite(S).any((0, 2)) | (Cf != 0).any((0, 2))) | (
            Fl != 0
        ).any((0, 2))
        res_core = type(res)(res.track_id[has], X[:, has], S[:, has], Cf[:, has], Fl[:, has], None, None)
        track_arrays_to_file(res_core, frames[a:b], t_ns[a:b], fps, rig.sha256(), source).save(
            out_store.part_path(i)
        )
        out_store.commit(i)
        del raw, res, res_core, X, S, Cf, Fl
        release_free_memory()
    return counts, rooms
