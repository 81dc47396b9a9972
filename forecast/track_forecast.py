"""A model's forecast of a track file: every track's next seconds by a forecasting checkpoint, and why none
could be forecast. :func:`roomcap.forecast.preview.preview` (the pipeline's entry, torch-free to import) and
``forecast sample`` call it; importing this module loads torch.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from roomcap.core.errors import InputError
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
    *,
    start_s: float | None = None,
    strict: bool = False,
) -> dict:
    """The next ``horizon_s`` of every track of ``track_file`` by the model of ``checkpoint``, from its last
    ``obs_s`` (default: the frames the model was trained on); the dict of
    :func:`roomcap.forecast.preview.preview`, plus ``stochastic`` (whether the samples differ: a
    deterministic model's one forecast is repeated ``n_samples`` times), ``obs_xyz_m (n_obs,K,J,3)``
    (the frames the model saw, NaN where unknown), ``truth_xyz_m (H,K,J,3)`` (the track after the
    forecast's start: NaN beyond its end), ``track_fps`` (the track file's own rate; the track is
    resampled to the model's ``fps``).

    ``start_s``: forecast from this time (seconds after the track's first frame; default its last frame), so
    that the rest of the track is the truth. ``strict`` (``forecast sample``): a track file the model cannot
    forecast as trained (shorter than its observation, nobody seen at the start) is an :class:`InputError`
    saying why and what to do; otherwise (the pipeline's preview) what can be forecast is."""
    clip = fdata.clip_from_trackfile(track_file)
    model, meta = load_checkpoint(checkpoint, skeleton=clip.skeleton)
    fps = float(meta["fps"])
    c = clip.resampled(fps)
    n_obs = int(round(obs_s * fps)) if obs_s else int(meta["config"].n_obs)
    H = max(1, int(round(horizon_s * fps)))
    T_all, K, J = c.xyz_m.shape[:3]
    T = T_all
    if start_s is not None:
        T = int(np.floor(start_s * fps + 1e-6)) + 1
        if not 1 <= T <= T_all:
            raise InputError(
                f"--start-s {start_s:g} is outside {track_file}, which spans 0 to {(T_all - 1) / fps:.2f} s "
                f"at {fps:g} Hz; give a time within it (or none: its last frame)."
            )
    lh, rh = fdata.hip_indices(fdata.get_skeleton(clip.skeleton).joint_names)
    if strict:
        why = _not_forecastable(c.xyz_m[:T], (lh, rh), n_obs, fps, str(meta["kind"]), track_file, clip.fps)
        if why:
            raise InputError(why)
    out = np.full((n_samples, H, K, J, 3), np.nan, np.float32)
    ws = c.xyz_m[max(0, T - n_obs) : T]
    if T:
        m = np.isfinite(ws).all(-1)
        present = m[-1, :, lh] & m[-1, :, rh]
        if present.any() and len(ws) >= 2:
            x = fdata._fill(ws[:, present], m[:, present])
            with torch.no_grad():
                y = forecast_world(
                    model, x[None], None, H, n_samples if getattr(model, "stochastic", False) else 1
                )
            out[:, :, present] = y[0] if y.shape[1] == n_samples else np.repeat(y[0], n_samples, 0)
    truth = np.full((H, K, J, 3), np.nan, np.float32)
    after = c.xyz_m[T : T + H]
    truth[: len(after)] = after
    tid = TrackFile.load(track_file).track_id
    return {
        "xyz_m": out,
        "t_s": np.arange(1, H + 1) / fps,
        "track_id": tid,
        "fps": fps,
        "joint_names": np.asarray(fdata.get_skeleton(clip.skeleton).joint_names),
        "model": meta["kind"],
        "stochastic": bool(getattr(model, "stochastic", False)),
        "obs_xyz_m": ws.astype(np.float32),
        "truth_xyz_m": truth,
        "track_fps": float(clip.fps),
    }


def _not_forecastable(
    xyz: np.ndarray, hips: tuple[int, int], n_obs: int, fps: float, kind: str, track_file, track_fps: float
) -> str:
    """Why the frames ``xyz (T,K,J,3)`` (at the model's ``fps``, up to the forecast's start) cannot be
    forecast as the model was trained, as a sentence with what to do; "" when they can."""
    T, K = xyz.shape[:2]
    window = f"the model ({kind}) looks at the last {n_obs} frames ({n_obs / fps:.1f} s at {fps:g} Hz)"
    resampled = f", resampled from its {track_fps:g} Hz" if abs(track_fps - fps) > 1e-6 else ""
    if T < n_obs:
        return (
            f"{track_file} is too short to forecast: it holds {T} frame{'s' if T != 1 else ''} "
            f"({T / fps:.2f} s at {fps:g} Hz{resampled}) up to the forecast's start, and {window}. A track "
            f"must be at least {n_obs / fps:.1f} s long ({n_obs} frames at {fps:g} Hz) before the forecast "
            f"starts: forecast a longer recording (or from a later --start-s), or pass "
            f"--obs-s {T / fps:.2f} or less to forecast from fewer frames than the model was trained on. "
            "Nothing was written."
        )
    if not np.isfinite(xyz[-1][:, list(hips)]).all((-1, -2)).any():
        return (
            f"none of the {K} tracks of {track_file} is seen (both hips) in its last frame, where every "
            f"forecast starts ({window}). Forecast a track file that ends while people are in view (or give "
            "--start-s at a time they are). Nothing was written."
        )
    return ""
