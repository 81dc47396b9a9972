"""A model's forecast of a track file: every track's next seconds by a forecasting checkpoint, and why none
could be forecast. :func:`forecast.runtime.preview.preview` (the pipeline's entry, torch-free to import) and
``forecast sample`` call it; importing this module loads torch.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.runtime import normalise as fdata
from roomcap.forecast.runtime.baselines import baseline_preview
from roomcap.forecast.runtime.checkpoint import load_checkpoint
from roomcap.forecast.runtime.predict import forecast_world
from roomcap.keypoints.skeletons import get_skeleton
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
    :func:`roomcap.forecast.runtime.preview.preview`, plus ``stochastic`` (whether the samples differ: a
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
    lh, rh = fdata.hip_indices(get_skeleton(clip.skeleton).joint_names)
    if strict:
        why = _not_forecastable(c.xyz_m[:T], (lh, rh), n_obs, fps, str(meta["model"]), track_file, clip.fps)
        if why:
            raise InputError(why)
    ws = c.xyz_m[max(0, T - n_obs) : T]
    out, _ = _forecast_window(model, ws, (lh, rh), H, n_samples)
    truth = np.full((H, K, J, 3), np.nan, np.float32)
    after = c.xyz_m[T : T + H]
    truth[: len(after)] = after
    tid = TrackFile.load(track_file).track_id
    return {
        "xyz_m": out,
        "t_s": np.arange(1, H + 1) / fps,
        "track_id": tid,
        "fps": fps,
        "joint_names": np.asarray(get_skeleton(clip.skeleton).joint_names),
        "model": meta["model"],
        "stochastic": bool(getattr(model, "stochastic", False)),
        "obs_xyz_m": ws.astype(np.float32),
        "truth_xyz_m": truth,
        "track_fps": float(clip.fps),
    }


def _forecast_window(
    model, ws: np.ndarray, hips: tuple[int, int], H: int, n_samples: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """The model's next ``H`` frames after the window ``ws (T,K,J,3)`` (world metres at the model's rate, NaN
    = unknown): ``(S,H,K,J,3)`` (NaN for the tracks not seen, both hips, in the window's last frame: the
    normalisation frame, eq. 3.8) and that mask ``(K,)``. Unknown frames are filled with the last known value
    (``normalise.fill``); a window of fewer than 2 frames is not forecast."""
    K, J = ws.shape[1:3]
    out = np.full((n_samples, H, K, J, 3), np.nan, np.float32)
    present = np.zeros(K, bool)
    if not len(ws):
        return out, present
    m = np.isfinite(ws).all(-1)
    present = m[-1, :, hips[0]] & m[-1, :, hips[1]]
    if present.any() and len(ws) >= 2:
        x = fdata.fill(ws[:, present], m[:, present])
        with torch.no_grad():
            S = n_samples if getattr(model, "stochastic", False) else 1
            y = forecast_world(model, x[None], None, H, S)
        out[:, :, present] = y[0] if y.shape[1] == n_samples else np.repeat(y[0], n_samples, 0)
    return out, present


def resample_recent(t_s: np.ndarray, xyz_m: np.ndarray, fps: float, n: int) -> np.ndarray:
    """The last ``n`` frames at ``fps`` of a track sampled at the irregular times ``t_s (T,)`` (increasing,
    seconds; a live track skips the frame sets its loop could not take): ``xyz_m (T,K,J,3)`` linearly
    interpolated in time onto ``t_s[-1] - k / fps`` (k < n, not before ``t_s[0]``), oldest first. NaN where
    either neighbour is NaN, as :meth:`roomcap.forecast.runtime.normalise.Clip.resampled`."""
    t = np.asarray(t_s, np.float64)
    x = np.asarray(xyz_m, np.float32)
    if not len(t):
        return x[:0]
    span = t[-1] - t[0]
    k = min(int(n), int(np.floor(span * fps + 1e-6)) + 1)
    grid = t[-1] - np.arange(k)[::-1] / fps
    i1 = np.clip(np.searchsorted(t, grid, side="left"), 0, len(t) - 1)
    i0 = np.clip(i1 - 1, 0, len(t) - 1)
    gap = t[i1] - t[i0]
    w = np.where(gap > 0, (grid - t[i0]) / np.where(gap > 0, gap, 1.0), 1.0)
    w = np.clip(w, 0.0, 1.0)[:, None, None, None].astype(np.float32)
    return (1 - w) * x[i0] + w * x[i1]


def forecast_recent(
    model, meta: dict, t_s: np.ndarray, xyz_m: np.ndarray, horizon_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A live track's next ``horizon_s`` from its recent frames ``xyz_m (T,K,J,3)`` (body19, world metres, NaN
    = unknown) at the times ``t_s (T,)``: resampled to the model's rate (:func:`resample_recent`, its
    ``n_obs`` frames at most), forecast as :func:`forecast_tracks` does (:func:`_forecast_window`). Returns
    ``(xyz (H,K,J,3), t_s (H,) seconds after the last frame, present (K,))``. ``model`` None: the
    constant-velocity baseline (:func:`forecast.runtime.baselines.baseline_preview`) at ``meta["fps"]``."""
    fps = float(meta["fps"])
    H = max(1, int(round(horizon_s * fps)))
    n_obs = int(meta["config"].n_obs) if "config" in meta else int(round(2.0 * fps))
    ws = resample_recent(t_s, xyz_m, fps, n_obs)
    if model is None:
        out, present = baseline_preview(ws.astype(np.float64), fps, H, "constant_velocity")
        return np.moveaxis(out, 1, 0), np.arange(1, H + 1) / fps, present
    lh, rh = fdata.hip_indices(get_skeleton("body19").joint_names)
    out, present = _forecast_window(model, ws, (lh, rh), H, 1)
    return out[0], np.arange(1, H + 1) / fps, present


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
