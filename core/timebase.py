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
