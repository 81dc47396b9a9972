"""Forecast preview for the pipeline: the next seconds of every track in a track file.

``preview(track_file, horizon_s)`` -> dict with ``xyz_m (S,H,K,J,3)`` world metres (NaN for tracks not
present at the last frame), ``t_s (H,)`` seconds after the last frame, ``track_id (K,)``, ``fps`` (25),
``joint_names``, ``model``. Uses the shipped GRU checkpoint unless ``checkpoint`` is given; torch is only
imported here, inside forecast/.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from capture.fileio import save_npz, schema_tag
from forecast import data as fdata

CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
DEFAULT_CHECKPOINT = CHECKPOINT_DIR / "gru_cmu.pt"
FORECAST_SCHEMA, FORECAST_VERSION = "forecast", 1


def preview(
    track_file: str | os.PathLike,
    horizon_s: float = 1.0,
    checkpoint: str | os.PathLike | None = None,
    n_samples: int = 1,
    obs_s: float | None = None,
) -> dict:
    import torch

    from forecast.predict import forecast_world
    from forecast.train import load_checkpoint

    clip = fdata.clip_from_trackfile(track_file)
    model, meta = load_checkpoint(checkpoint or DEFAULT_CHECKPOINT, skeleton=clip.skeleton)
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
    from track.trackfile import TrackFile

    tid = TrackFile.load(track_file).track_id
    return {
        "xyz_m": out,
        "t_s": np.arange(1, H + 1) / fps,
        "track_id": tid,
        "fps": fps,
        "joint_names": np.asarray(fdata.get_skeleton(clip.skeleton).joint_names),
        "model": meta["kind"],
    }


def save_forecast(path: str | os.PathLike, fc: dict) -> None:
    """Write a preview/sample result as ``forecast/1`` npz."""
    save_npz(path, {"schema": schema_tag(FORECAST_SCHEMA, FORECAST_VERSION), **fc})
