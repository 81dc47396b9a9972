"""The checkpoint-free forecasts of a track (constant and zero velocity) in numpy, torch-free: the
pipeline's preview (:mod:`roomcap.forecast.runtime.preview`) and the live page's fallback
(:mod:`roomcap.forecast.runtime.track_forecast`)."""

from __future__ import annotations

import numpy as np

from roomcap.forecast.runtime.registry import baseline

PREVIEW_VEL_WINDOW_S = 0.2  # root velocity = mean over the last 0.2 s


def baseline_preview(xyz: np.ndarray, fps: float, H: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """The preview without a checkpoint, in numpy at the track file's own rate: xyz (T,K,J,3) world metres ->
    future (K,H,J,3) for the tracks present in the last frame, and that mask (K,). ``constant_velocity``:
    the last pose moved along the root velocity on the floor (root = mean of the seen joints, velocity over
    the last ``PREVIEW_VEL_WINDOW_S``; Tanke 2024, sec. 6.4.4 baselines); ``zero_velocity``: the last
    pose.
    Unlike ``forecast.models.ConstantVelocity`` (per-joint velocities, torch, 25 Hz windows) it takes
    tracks with missing joints as they are."""
    T, K, J, _ = xyz.shape
    out = np.full((K, H, J, 3), np.nan, np.float32)
    if T == 0:
        return out, np.zeros(K, bool)
    last = xyz[-1]
    present = np.isfinite(last).all(-1).any(-1)
    seen = np.isfinite(xyz).all(-1, keepdims=True)
    n_seen = seen.sum(2)
    root = np.where(n_seen > 0, np.where(seen, xyz, 0).sum(2) / np.maximum(n_seen, 1), np.nan)  # (T,K,3)
    n = max(1, min(T - 1, int(round(PREVIEW_VEL_WINDOW_S * fps))))
    if baseline(kind).moves and T >= 2:
        v = (root[-1] - root[-1 - n]) / n  # metres per frame
        v = np.where(np.isfinite(v), v, 0.0)
        v[:, 2] = 0.0  # people walk on the floor
    else:
        v = np.zeros((K, 3))
    steps = np.arange(1, H + 1)[None, :, None, None]
    out[:] = last[:, None] + steps * v[:, None, None, :]
    out[~present] = np.nan
    return out.astype(np.float32), present
