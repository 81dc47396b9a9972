"""Adapters between the pipeline and stage packages whose APIs do not fit the runner directly.

* forecast preview: ``forecast.preview.preview`` gives ``xyz_m (S,H,K,J,3)`` at the checkpoint's rate;
  the report wants one future per track, ``xyz_m (K,H,J,3)`` starting after the last tracked frame.
  Without a trained checkpoint (``forecast/checkpoints/gru_cmu.pt``) the preview is the constant-velocity
  baseline of the body root (Tanke 2024, sec. 6.4.4 baselines), computed here in numpy.
* particle tracker: ``track.stage.track_session_particle`` when the track package provides it.

The preview file ``forecast/preview.npz`` (schema ``forecast_preview/1``): ``xyz_m (K,H,J,3)`` world metres,
``track_id (K,)``, ``start_index`` (frame index of the last observed frame), ``fps`` of the forecast,
``t_s (H,)`` seconds after the last frame, ``model``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from capture.fileio import save_npz, schema_tag
from capture.session import SessionLayout
from forecast.preview import preview
from track.trackfile import TrackFile

log = logging.getLogger(__name__)

PREVIEW_SCHEMA, PREVIEW_VERSION = "forecast_preview", 1
BASELINES = ("constant_velocity", "zero_velocity")
_VEL_WINDOW_S = 0.2  # root velocity = mean over the last 0.2 s


def forecast_model(model: str) -> tuple[str, Path | None]:
    """``(kind, checkpoint)`` for a forecast model name: "default" (the shipped GRU if present, else the
    constant-velocity baseline), a baseline name, or a checkpoint path."""
    if model in BASELINES:
        return model, None
    if model == "default":
        try:
            from forecast.preview import DEFAULT_CHECKPOINT
        except ImportError:
            return "constant_velocity", None
        return (
            ("checkpoint", Path(DEFAULT_CHECKPOINT))
            if Path(DEFAULT_CHECKPOINT).exists()
            else ("constant_velocity", None)
        )
    path = Path(model)
    if not path.exists():
        raise FileNotFoundError(
            f"forecast model '{model}' is neither {['default', *BASELINES]} nor an existing checkpoint file."
        )
    return "checkpoint", path


def _baseline(xyz: np.ndarray, fps: float, H: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """xyz (T,K,J,3) -> future (K,H,J,3) for tracks present in the last frame, and that mask (K,)."""
    T, K, J, _ = xyz.shape
    out = np.full((K, H, J, 3), np.nan, np.float32)
    if T == 0:
        return out, np.zeros(K, bool)
    last = xyz[-1]
    present = np.isfinite(last).all(-1).any(-1)
    seen = np.isfinite(xyz).all(-1, keepdims=True)
    n_seen = seen.sum(2)
    root = np.where(n_seen > 0, np.where(seen, xyz, 0).sum(2) / np.maximum(n_seen, 1), np.nan)  # (T,K,3)
    n = max(1, min(T - 1, int(round(_VEL_WINDOW_S * fps))))
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


def write_preview(tracks_path: Path, out_path: Path, horizon_s: float, model: str) -> Path:
    """Forecast every track present at the last frame ``horizon_s`` ahead and write ``out_path``."""

    kind, checkpoint = forecast_model(model)
    tf = TrackFile.load(tracks_path)
    start = int(tf.frame_index[-1]) if tf.n_frames else 0
    if kind == "checkpoint":
        import torch

        torch.set_num_threads(1)  # the same bytes on every machine and executor
        fc = preview(tracks_path, horizon_s, checkpoint=checkpoint)
        xyz = np.moveaxis(np.asarray(fc["xyz_m"][0], np.float32), 1, 0)  # (H,K,J,3) -> (K,H,J,3)
        fps, t_s, name = float(fc["fps"]), np.asarray(fc["t_s"], np.float64), str(fc["model"])
    else:
        fps = float(tf.fps)
        H = max(1, int(round(horizon_s * fps)))
        xyz, _ = _baseline(np.asarray(tf.xyz_m, np.float64), fps, H, kind)
        t_s, name = np.arange(1, H + 1) / fps, kind
    save_npz(
        out_path,
        {
            "schema": schema_tag(PREVIEW_SCHEMA, PREVIEW_VERSION),
            "xyz_m": xyz,
            "track_id": np.asarray(tf.track_id, np.int64),
            "start_index": np.int64(start),
            "fps": np.float64(fps),
            "t_s": t_s,
            "model": name,
        },
    )
    return out_path


def track_particle(lay: SessionLayout, options: dict) -> Path:
    """The chapter-5 particle tracker on the session's detections (``track.stage``)."""
    try:
        from track.stage import track_session_particle
    except ImportError:
        raise RuntimeError(
            "the particle tracker's session stage (track.stage.track_session_particle) is not in "
            "this build; use --tracker greedy."
        ) from None
    return track_session_particle(lay.root, options or None)
