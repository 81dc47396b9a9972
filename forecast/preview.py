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

from core.fileio import save_npz, schema_tag
from forecast import data as fdata
from track.trackfile import TrackFile

CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
DEFAULT_CHECKPOINT = CHECKPOINT_DIR / "gru_cmu.pt"
FORECAST_SCHEMA, FORECAST_VERSION = "forecast", 1
BASELINES = ("constant_velocity", "zero_velocity")  # the checkpoint-free previews (baseline_preview)
PREVIEW_VEL_WINDOW_S = 0.2  # root velocity = mean over the last 0.2 s


def shipped_checkpoints() -> list[str]:
    """The body19 forecast checkpoints shipped in forecast/checkpoints (not the characteristic-pose one, not
    the CMU 8-action benchmark's own model)."""
    return [
        str(p)
        for p in sorted(CHECKPOINT_DIR.glob("*.pt"))
        if not p.name.startswith(("characteristic", "cmu8_"))
    ]


def _load_model(checkpoint: str | os.PathLike | None, skeleton: str) -> tuple:
    """The model of ``checkpoint`` (default: the shipped GRU) for ``skeleton``, and its metadata."""
    from forecast.checkpoint import load_checkpoint  # lazy: loads torch

    return load_checkpoint(checkpoint or DEFAULT_CHECKPOINT, skeleton=skeleton)


def preview(
    track_file: str | os.PathLike,
    horizon_s: float = 1.0,
    checkpoint: str | os.PathLike | None = None,
    n_samples: int = 1,
    obs_s: float | None = None,
) -> dict:
    import torch  # lazy: loads torch

    from forecast.predict import forecast_world  # lazy: loads torch

    clip = fdata.clip_from_trackfile(track_file)
    model, meta = _load_model(checkpoint, clip.skeleton)
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
    track_file: str | os.PathLike, checkpoint: str | os.PathLike | None = None, obs_s: float | None = None
) -> str:
    """Why :func:`preview` forecast none of the tracks of ``track_file``, as a sentence with what to do: the
    tracks are shorter than the frames the model needs, or nobody is seen at the last frame (where every
    forecast starts)."""
    clip = fdata.clip_from_trackfile(track_file)
    _, meta = _load_model(checkpoint, clip.skeleton)
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
    if kind == "constant_velocity" and T >= 2:
        v = (root[-1] - root[-1 - n]) / n  # metres per frame
        v = np.where(np.isfinite(v), v, 0.0)
        v[:, 2] = 0.0  # people walk on the floor
    else:
        v = np.zeros((K, 3))
    steps = np.arange(1, H + 1)[None, :, None, None]
    out[:] = last[:, None] + steps * v[:, None, None, :]
    out[~present] = np.nan
    return out.astype(np.float32), present


def save_forecast(path: str | os.PathLike, fc: dict) -> None:
    """Write a preview/sample result as ``forecast/1`` npz."""
    save_npz(path, {"schema": schema_tag(FORECAST_SCHEMA, FORECAST_VERSION), **fc})
