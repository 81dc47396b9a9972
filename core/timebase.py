"""The frame rate of a stream of frames from its timestamps: the one estimate every stage uses."""

from __future__ import annotations

import numpy as np


def frame_rate_hz(t_ns: np.ndarray, frame_index: np.ndarray | None = None) -> float | None:
    """The median frame rate of frames stamped ``t_ns`` (0 = no timestamp); with ``frame_index``, each
    interval is divided by the frames it spans, so dropped frames do not lower the rate. None when no two
    stamped frames follow each other.

    >>> frame_rate_hz(np.array([0, 40_000_000, 80_000_000, 120_000_000]))  # the first frame has no stamp
    25.0
    >>> frame_rate_hz(np.array([0, 40_000_000, 120_000_000]), np.array([0, 1, 3]))  # frame 2 was dropped
    25.0
    >>> frame_rate_hz(np.array([0, 0])) is None
    True
    """
    t = np.asarray(t_ns, np.int64)
    keep = t != 0
    t = t[keep]
    dt = np.diff(t).astype(np.float64)
    if frame_index is not None:
        df = np.diff(np.asarray(frame_index)[keep]).astype(np.float64)
        ok = (dt > 0) & (df > 0)
        per_frame = dt[ok] / df[ok]
    else:
        per_frame = dt[dt > 0]
    return float(1e9 / np.median(per_frame)) if len(per_frame) else None


def timestamps_backwards(frame_index: np.ndarray, t_ns: np.ndarray) -> str | None:
    """Where stamped frames (``t_ns`` != 0) go back in time, in words naming the frames, or None when they
    never do. ``frame_index`` numbers the rows.

    >>> timestamps_backwards(np.array([0, 1, 2, 3]), np.array([10, 20, 15, 30])) is None
    False
    >>> timestamps_backwards(np.array([0, 1, 2, 3]), np.array([10, 20, 15, 30]))
    'timestamps go backwards at frame 2 (15 ns, after frame 1 at 20 ns)'
    >>> timestamps_backwards(np.array([4, 5, 6, 7, 8]), np.array([10, 5, 0, 3, 2]))
    'timestamps go backwards at frame 5 (5 ns, after frame 4 at 10 ns) and at 2 more frames (7, 8)'
    >>> timestamps_backwards(np.array([0, 1]), np.array([0, 0])) is None
    True
    """
    fi, t = np.asarray(frame_index), np.asarray(t_ns, np.int64)
    have = np.flatnonzero(t != 0)
    back = np.flatnonzero(np.diff(t[have]) < 0)
    if not len(back):
        return None
    k, p = have[back[0] + 1], have[back[0]]
    out = (
        f"timestamps go backwards at frame {int(fi[k])} ({int(t[k])} ns, after frame {int(fi[p])} "
        f"at {int(t[p])} ns)"
    )
    if len(back) > 1:
        more = [int(fi[have[b + 1]]) for b in back[1:]]
        shown = ", ".join(map(str, more[:5])) + (", ..." if len(more) > 5 else "")
        out += f" and at {len(more)} more frame{'s' if len(more) > 1 else ''} ({shown})"
    return out


# A rate below this many frames a second is a sparse clock: snapshots (a time-lapse, a motion-triggered
# recording), not a slow camera. The stages then run their clock at SNAPSHOT_CLOCK_FPS, so that frames a
# fraction of a second apart (a trigger's burst) are linked as video and every gap longer than a tracker's
# ``max_gap_s`` is a pause of the recorder, across which nothing is predicted, filled or smoothed.
SPARSE_BELOW_HZ = 1.0
SNAPSHOT_CLOCK_FPS = 25.0


def is_sparse(rate_hz: float) -> bool:
    """Whether frames at ``rate_hz`` (stated or estimated) are snapshots rather than a video."""
    return 0 < rate_hz < SPARSE_BELOW_HZ


def clock_fps(rate_hz: float) -> float:
    """The rate of the stages' clock for frames at ``rate_hz``: the rate itself, or for a sparse clock
    :data:`SNAPSHOT_CLOCK_FPS` (its gaps in seconds, not the median gap, say what can be linked).

    >>> clock_fps(25.0), clock_fps(1 / 75)
    (25.0, 25.0)
    """
    return SNAPSHOT_CLOCK_FPS if is_sparse(rate_hz) else float(rate_hz)


def _duration(s: float) -> str:
    for unit, n in (("d", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if s >= n:
            return f"{s / n:.3g} {unit}"
    return f"{s:.3g} s"


def gap_statistics(t_s: np.ndarray) -> str:
    """The gaps between consecutive frames at times ``t_s`` (seconds) in words: median, shortest, longest.

    >>> gap_statistics(np.array([0.0, 1.0, 2.0, 90_002.0]))
    '4 frames a median 1 s apart (from 1 s to 1.04 d)'
    """
    d = np.diff(np.asarray(t_s, np.float64))
    if not len(d):
        return f"{len(t_s)} frames"
    return (
        f"{len(t_s)} frames a median {_duration(float(np.median(d)))} apart "
        f"(from {_duration(float(d.min()))} to {_duration(float(d.max()))})"
    )
