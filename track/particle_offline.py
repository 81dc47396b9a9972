"""The particle tracker over a whole sequence, offline: :func:`track_sequence` steps the filter through
the frames, :func:`gather_estimates` collects its per-frame estimates, and :func:`finish_tracks` cleans
them up (trailing coasting frames and short tracks dropped, smoothing in time)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from roomcap.core.progress import Progress
from roomcap.track.greedy import (
    frame_times_s,
    long_enough,
    pause_clock,
    segment_frames,
    smooth_segments,
    sparse_time_warning,
)
from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_types import FrameEstimate
from roomcap.track.trackfile import SMOOTHED

log = logging.getLogger(__name__)


@dataclass
class TrackArrays:
    """Dense output of a sequence: T frames, K tracks (columns sorted by id)."""

    track_id: np.ndarray  # (K,)
    xyz_m: np.ndarray  # (T,K,J,3) NaN where unknown
    std_m: np.ndarray  # (T,K,J)
    confidence: np.ndarray  # (T,K,J)
    flags: np.ndarray  # (T,K,J) uint8
    n_views: np.ndarray  # (T,K,J)
    time_s: np.ndarray  # (T,) seconds spent in step() per frame


def check_times(frames: np.ndarray, t_ns: np.ndarray | None) -> None:
    """Timestamps ``t_ns`` (T,) must increase (all zeros = none: times from the frame numbers); the error
    names the first frame whose time does not follow the previous frame's."""
    T = len(frames)
    if t_ns is not None and T > 1 and np.any(t_ns) and not (np.diff(np.asarray(t_ns, np.int64)) > 0).all():
        bad = int(np.flatnonzero(np.diff(np.asarray(t_ns, np.int64)) <= 0)[0]) + 1
        raise ValueError(
            f"frame {int(frames[bad])}: its timestamp does not follow the previous frame's; "
            "t_ns must increase (all zeros = no timestamps: times from the frame numbers)"
        )


def warn_sparse_time(t_s: np.ndarray, cfg: ParticleConfig, fps: float) -> None:
    """Say so when the frames are snapshots too far apart to link (``sparse_time_warning``)."""
    warn = sparse_time_warning(
        pause_clock(t_s, cfg.max_gap_s, fps)[1], cfg.max_gap_s, min_evidence_frames(cfg, fps), t_s
    )
    if warn:
        log.warning("particle tracker: %s", warn)


def track_sequence(
    tracker: ParticleTracker,
    kp: np.ndarray,
    sc: np.ndarray,
    frames: np.ndarray | None = None,
    progress: Progress | None = None,
    maps_at=None,
    t_ns: np.ndarray | None = None,
) -> TrackArrays:
    """Run the filter over a sequence. kp: (T,C,D,J,2) undistorted px (NaN = missing), sc: (T,C,D,J).
    ``maps_at(t)``: optional, the C :class:`roomcap.track.observation.CameraMaps` (or None) of frame t. Frame
    times come from ``t_ns`` (T,), else from the frame numbers ``frames`` at the tracker's rate
    (:func:`roomcap.track.greedy.frame_times_s`); smoothing never bridges a pause (``max_gap_s``).

    Applies the offline clean-up of the config: coasting frames after a track's last evidence are dropped
    (``trim_coast``) and tracks with less evidence than ``min_track_s`` are removed.
    """
    import time

    cfg = tracker.config
    T = len(kp)
    frames = np.arange(T) if frames is None else np.asarray(frames)
    if len(frames) != T or (t_ns is not None and len(t_ns) != T):
        raise ValueError(f"frames and t_ns must have one entry per frame ({T})")
    check_times(frames, t_ns)
    t_s = frame_times_s(frames, t_ns, tracker.fps)
    warn_sparse_time(t_s, cfg, tracker.fps)
    J = tracker.skeleton.n_joints
    per_frame: list[FrameEstimate] = []
    times = np.zeros(T)
    for t in range(T):
        t0 = time.perf_counter()
        per_frame.append(
            tracker.step(kp[t], sc[t], t, None if maps_at is None else maps_at(t), float(t_s[t]))
        )
        times[t] = time.perf_counter() - t0
        if progress is not None:
            progress("track", t + 1, T)
    raw = gather_estimates(per_frame, J)
    return finish_tracks(raw, t_s, cfg, tracker.fps, times=times)


@dataclass
class RawEstimates:
    """The filter's per-frame output on a dense (T,K) grid before the offline clean-up (``seen`` (T,K):
    the track had evidence; columns sorted by id)."""

    track_id: np.ndarray  # (K,)
    xyz_m: np.ndarray  # (T,K,J,3)
    std_m: np.ndarray  # (T,K,J)
    confidence: np.ndarray  # (T,K,J)
    flags: np.ndarray  # (T,K,J) uint8
    n_views: np.ndarray  # (T,K,J)
    seen: np.ndarray  # (T,K) bool


def gather_estimates(per_frame: list[FrameEstimate], J: int) -> RawEstimates:
    """The per-frame estimates of T frames on one grid of the ids they contain."""
    T = len(per_frame)
    ids = sorted({int(i) for e in per_frame for i in e.track_id})
    col = {tid: k for k, tid in enumerate(ids)}
    K = len(ids)
    xyz = np.full((T, K, J, 3), np.nan, np.float32)
    std = np.full((T, K, J), np.nan, np.float32)
    conf = np.zeros((T, K, J), np.float32)
    flags = np.zeros((T, K, J), np.uint8)
    nv = np.zeros((T, K, J), np.int16)
    seen = np.zeros((T, K), bool)
    for t, e in enumerate(per_frame):
        if len(e.track_id) == 0:
            continue
        ks = np.array([col[int(i)] for i in e.track_id])
        xyz[t, ks], std[t, ks], conf[t, ks], flags[t, ks], nv[t, ks] = (
            e.xyz_m,
            e.std_m,
            e.confidence,
            e.flags,
            e.n_views,
        )
        seen[t, ks] = e.evidence
    return RawEstimates(np.asarray(ids, np.int64), xyz, std, conf, flags, nv, seen)


def min_evidence_frames(cfg: ParticleConfig, fps: float) -> int:
    """``min_track_s`` in frames at ``fps``: a track with less evidence is dropped (:func:`finish_tracks`)."""
    return max(1, int(round(cfg.min_track_s * fps)))


def finish_tracks(
    raw: RawEstimates,
    t_s: np.ndarray,
    cfg: ParticleConfig,
    fps: float,
    times: np.ndarray | None = None,
    evidence_frames: np.ndarray | None = None,
    room_frames: np.ndarray | None = None,
) -> TrackArrays:
    """The offline clean-up of :func:`track_sequence` on the raw estimates of T frames at times ``t_s``
    (T,) (seconds, the session's clock): frames coasted across a pause are removed, then trailing coasting
    frames (``trim_coast``), then the smoothing (``smooth_sigma_s``), then tracks with less evidence than
    ``min_track_s`` (:func:`roomcap.track.greedy.long_enough`: not where the recorder paused sooner).
    ``evidence_frames`` (K,) and ``room_frames`` (K,): each track's evidence frames over the whole session
    and the longest stretch without a pause among them, when ``raw`` is a window of it (default: from
    ``raw``). Each value depends only on the frames within
    ``end_after_s`` (on the tracks' clock) plus the smoothing radius of it, so a window with that margin
    gives its middle frames exactly as the whole session does (:mod:`roomcap.track.particle_chunked`).
    Changes ``raw``'s arrays in place."""
    xyz, std, conf, flags = raw.xyz_m, raw.std_m, raw.confidence, raw.flags  # changed in place
    nv, seen, ids = raw.n_views, raw.seen, raw.track_id
    T, K = seen.shape
    # frames coasted after a pause of the recorder (no evidence since before it): the filter's guess across
    # an unknown stretch of time, never output (as the greedy tracker never fills across a pause)
    _, pauses = pause_clock(t_s, cfg.max_gap_s, fps)
    last_ev = np.maximum.accumulate(np.where(seen, np.arange(T)[:, None], -1), axis=0)  # (T,K)
    across = ~seen & (last_ev >= 0) & (pauses[:, None] != pauses[np.maximum(last_ev, 0)])
    xyz[across], std[across], conf[across], flags[across] = np.nan, np.nan, 0, 0
    if cfg.trim_coast:
        for k in range(K):  # drop every frame after the last evidence of each contiguous segment
            alive = np.isfinite(xyz[:, k]).all(-1).any(-1)
            t = 0
            while t < T:
                if not alive[t]:
                    t += 1
                    continue
                s = t
                while t < T and alive[t]:
                    t += 1
                ev = np.flatnonzero(seen[s:t, k])
                cut = s + (ev[-1] + 1 if len(ev) else 0)
                xyz[cut:t, k], std[cut:t, k], conf[cut:t, k], flags[cut:t, k] = np.nan, np.nan, 0, 0
    sigma_s = cfg.smooth_sigma_s or 0.0
    if sigma_s > 0:
        known = np.isfinite(xyz).all(-1)
        xyz = smooth_segments(xyz, t_s, sigma_s, cfg.max_gap_s, fps).astype(np.float32)
        flags = np.where(known, flags | SMOOTHED, flags).astype(np.uint8)
    n_ev = seen.sum(0) if evidence_frames is None else np.asarray(evidence_frames)
    if room_frames is None:
        room_frames = np.where(seen, segment_frames(pauses)[:, None], 0).max(0, initial=0)
    keep = long_enough(n_ev, room_frames, min_evidence_frames(cfg, fps))
    return TrackArrays(
        ids[keep],
        xyz[:, keep],
        std[:, keep],
        conf[:, keep],
        flags[:, keep],
        nv[:, keep],
        np.zeros(T) if times is None else times,
    )
