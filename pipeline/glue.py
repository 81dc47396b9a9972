"""Adapters between the pipeline and stage packages whose APIs do not fit the runner directly.

* forecast preview: ``forecast.preview.preview`` gives ``xyz_m (S,H,K,J,3)`` at the checkpoint's rate;
  the report wants one future per track, ``xyz_m (K,H,J,3)`` starting after the last tracked frame.
  Without a trained checkpoint (``forecast/checkpoints/gru_cmu.pt``) the preview is the forecast package's
  torch-free baseline ``forecast.preview.baseline_preview`` (the last pose moved along the root velocity).
* particle tracker: ``track.stage.track_session_particle`` when the track package provides it.

The preview file ``forecast/preview.npz`` (schema ``forecast_preview/1``): ``xyz_m (K,H,J,3)`` world metres,
``track_id (K,)``, ``start_index`` (frame index of the last observed frame), ``fps`` of the forecast,
``t_s (H,)`` seconds after the last frame, ``model``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from capture.session import SessionLayout
from core.fileio import save_npz, schema_tag
from forecast.preview import BASELINES, DEFAULT_CHECKPOINT, baseline_preview, preview
from track.trackfile import TrackFile

log = logging.getLogger(__name__)

PREVIEW_SCHEMA, PREVIEW_VERSION = "forecast_preview", 1


def forecast_model(model: str) -> tuple[str, Path | None]:
    """``(kind, checkpoint)`` for a forecast model name: "default" (the shipped GRU if present, else the
    constant-velocity baseline), a baseline name, or a checkpoint path."""
    if model in BASELINES:
        return model, None
    if model == "default":
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


def write_preview(tracks_path: Path, out_path: Path, horizon_s: float, model: str) -> Path:
    """Forecast every track present at the last frame ``horizon_s`` ahead and write ``out_path``."""

    kind, checkpoint = forecast_model(model)
    tf = TrackFile.load(tracks_path)
    start = int(tf.frame_index[-1]) if tf.n_frames else 0
    if kind == "checkpoint":
        import torch  # lazy: loads torch

        torch.set_num_threads(1)  # the same bytes on every machine and executor
        fc = preview(tracks_path, horizon_s, checkpoint=checkpoint)
        xyz = np.moveaxis(np.asarray(fc["xyz_m"][0], np.float32), 1, 0)  # (H,K,J,3) -> (K,H,J,3)
        fps, t_s, name = float(fc["fps"]), np.asarray(fc["t_s"], np.float64), str(fc["model"])
    else:
        fps = float(tf.fps)
        H = max(1, int(round(horizon_s * fps)))
        xyz, _ = baseline_preview(np.asarray(tf.xyz_m, np.float64), fps, H, kind)
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
