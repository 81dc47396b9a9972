"""A model's forecast of a track file: every track's next seconds by a forecasting checkpoint, and why none
could be forecast. :func:`roomcap.forecast.preview.preview` (the pipeline's entry, torch-free to import) and
``forecast sample`` call it; importing this module loads torch.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from roomcap.forecast import data as fdata
from roomcap.forecast.checkpoint import load_checkpoint
from roomcap.forecast.predict import forecast_world
from roomcap.track.trackfile import TrackFile


def forecast_tracks(
    track_file: str | os.PathLike,
    horizon_s: float,
    checkpoint: str | os.PathLike,
    n_samples: int = 1,
    obs_s: float | None = None,
) -> dict:
    """The next ``horizon_s`` of every track of ``track_file`` by the model of ``checkpoint``, from its last
    ``obs_s`` (default: the frames the model was trained on); the dict of
    :func:`roomcap.forecast.preview.preview`."""
    clip = fdata.clip_from_trackfile(track_file)
    model, meta = load_checkpoint(checkpoint, skeleton=clip.skeleton)
    fps = float(meta["fps"])
    c = clip.resampled(fps)
    n_obs = int(round(obs_s * fps)) if obs_s else int(meta["config"].n_obs)
    H = max(1, int(round(horizon_s * fps)))
    T, K = c.xyz_m.shape[:2]
    J = c.xyz_m.shape[2]
    out = np.full((n_samples, H, K, J, 3), np.nan, np.float32)
    if T:
        ws = c.xyz_m[max(0, T - n_obs) :]
        m = np.isfinite(ws).all(-1)
        lh, rh = fdata.hip_indices(fdata.get_skeleton(clip.skeleton).joint_names)
        present = m[-1, :, lh] & m[-1, :, rh]
        if present.any() and len(ws) >= 2:
            x = fdata._fill(ws[:, present], m[:, present])
            with torch.no_grad():
                y = forecast_world(
                    model, x[None], None, H, n_samples if getattr(model, "stochastic", False) else 1
                )
            out[:, :, present] = y[0] if y.shape[1] == n_samples else np.repeat(y[0], n_samples, 0)
    tid = TrackFile.load(track_file).track_id
    return {
        "xyz_m": out,
        "t_s": np.arange(1, H + 1) / fps,
        "track_id": tid,
        "fps": fps,
        "joint_names": np.asarray(fdata.get_skeleton(clip.skeleton).joint_names),
        "model": meta["kind"],
    }


def no_forecast_reason(
    track_file: str | os.PathLike, checkpoint: str | os.PathLike, obs_s: float | None = None
) -> str:
    """Why :func:`forecast_tracks` forecast none of the tracks of ``track_file``, as a sentence with what to
    do: the tracks are shorter than the frames the model needs, or nobody is seen at the last frame (where
    every forecast starts); "" when some track can be forecast."""
    clip = fdata.clip_from_trackfile(track_file)
    _, meta = load_checkpoint(checkpoint, skeleton=clip.skeleton)
    fps = float(meta["fps"])
    c = clip.resampled(fps)
    n_obs = int(round(obs_s * fps)) if obs_s else int(meta["config"].n_obs)
    T, K = c.xyz_m.shape[:2]
    lh, rh = fdata.hip_indices(fdata.get_skeleton(clip.skeleton).joint_names)
    hips = np.isfinite(c.xyz_m[:, :, [lh, rh]]).all((-1, -2))  # (T,K) both hips seen
    seen_until_end = np.zeros(K, int)  # frames each track is seen up to the last frame
    for k in range(K):
        while seen_until_end[k] < T and hips[T - 1 - seen_until_end[k], k]:
            seen_until_end[k] += 1
    longest = int(seen_until_end.max(initial=0))
    if T and longest >= 2:
        return ""
    window = (
        f"the model ({meta['kind']}) looks at the last {n_obs} frames ({n_obs / fps:.1f} s at {fps:g} Hz)"
    )
    if T < 2 or (longest == 1 and hips[-1].any()):
        return (
            f"{track_file} is too short to forecast: it holds {T} frame{'s' if T != 1 else ''} "
            f"({T / fps:.2f} s at {fps:g} Hz), and {window}. A track must be seen (both hips) in at least "
            f"its last 2 frames ({2 / fps:.2f} s), and in {n_obs} ({n_obs / fps:.1f} s) for the forecast the "
            "model was trained for: forecast a longer recording."
        )
    return (
        f"none of the {K} tracks of {track_file} is seen (both hips) in its last frame, where every forecast "
        f"starts ({window}). Forecast a track file that ends while people are in view."
    )
