"""Forecast preview for the pipeline: the next seconds of every track in a track file.

``write_preview`` is the pipeline's forecast stage: ``forecast/preview.npz`` (schema
``forecast_preview/1``): ``xyz_m (K,H,J,3)`` world metres, ``track_id (K,)``, ``start_index`` (frame
index of the last observed frame), ``fps`` of the forecast, ``t_s (H,)`` seconds after the last frame,
``model``, ``joint_names (J,)``, ``stochastic`` (bool: the model draws samples); a stochastic model also
writes ``samples_xyz_m (S,K,H,J,3)``, its S draws (``xyz_m`` is the first). Without a trained checkpoint
the torch-free ``baseline_preview`` (deterministic).

``preview(track_file, horizon_s)`` -> dict with ``xyz_m (S,H,K,J,3)`` world metres (NaN for tracks not
present at the last frame), ``t_s (H,)`` seconds after the last frame, ``track_id (K,)``, ``fps`` (25),
``joint_names``, ``model``. Uses the shipped GRU checkpoint unless ``checkpoint`` is given. Importing this
module does not import torch: a model's forecast loads it (:mod:`roomcap.forecast.runtime.track_forecast`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from roomcap.core.fileio import save_npz, schema_tag
from roomcap.forecast.runtime.baselines import baseline_preview
from roomcap.track.trackfile import TrackFile

CHECKPOINT_DIR = Path(__file__).resolve().parents[1] / "checkpoints"
DEFAULT_CHECKPOINT = CHECKPOINT_DIR / "gru_cmuall.pt"  # picked over gru_cmu.pt on validation (BENCHMARKS)
FORECAST_SCHEMA, FORECAST_VERSION = "forecast", 1
BASELINES = ("constant_velocity", "zero_velocity")  # the checkpoint-free previews (baseline_preview)


def shipped_checkpoints() -> list[str]:
    """The body19 forecast checkpoints shipped in forecast/checkpoints (not the characteristic-pose one, not
    the behaviour model, not the CMU 8-action benchmark's own models)."""
    return [
        str(p)
        for p in sorted(CHECKPOINT_DIR.glob("*.pt"))
        if not p.name.startswith(("characteristic", "behaviour", "cmu8_"))
    ]


def preview(
    track_file: str | os.PathLike,
    horizon_s: float = 1.0,
    checkpoint: str | os.PathLike | None = None,
    n_samples: int = 1,
    obs_s: float | None = None,
) -> dict:
    """The forecast of every track of ``track_file`` by ``checkpoint`` (default: the shipped GRU); see the
    module docstring for what it holds."""
    from roomcap.forecast.runtime.track_forecast import forecast_tracks  # lazy: loads torch

    return forecast_tracks(track_file, horizon_s, checkpoint or DEFAULT_CHECKPOINT, n_samples, obs_s)


def save_forecast(path: str | os.PathLike, fc: dict) -> None:
    """Write a preview/sample result as ``forecast/1`` npz."""
    save_npz(path, {"schema": schema_tag(FORECAST_SCHEMA, FORECAST_VERSION), **fc})


# ----------------------------------------------------------------------------- the pipeline's forecast stage

PREVIEW_SCHEMA, PREVIEW_VERSION = "forecast_preview", 1
PREVIEW_SAMPLES = 16  # draws of a stochastic model (pipeline.config.ForecastConfig.samples)


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


def write_preview(
    tracks_path: Path, out_path: Path, horizon_s: float, model: str, n_samples: int = PREVIEW_SAMPLES
) -> Path:
    """Forecast every track present at the last frame ``horizon_s`` ahead and write ``out_path``; a
    stochastic model draws ``n_samples`` forecasts (seeded: the same track gives the same file)."""

    kind, checkpoint = forecast_model(model)
    tf = TrackFile.load(tracks_path)
    start = int(tf.frame_index[-1]) if tf.n_frames else 0
    extra: dict = {}
    if checkpoint is not None:
        import torch  # lazy: loads torch

        torch.set_num_threads(1)  # the same bytes on every machine and executor
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            fc = preview(tracks_path, horizon_s, checkpoint=checkpoint, n_samples=max(1, int(n_samples)))
        samples = np.moveaxis(np.asarray(fc["xyz_m"], np.float32), 2, 1)  # (S,H,K,J,3) -> (S,K,H,J,3)
        xyz = samples[0]
        fps, t_s, name = float(fc["fps"]), np.asarray(fc["t_s"], np.float64), str(fc["model"])
        stochastic = bool(fc.get("stochastic", False))
        names = np.asarray(fc["joint_names"])
        if stochastic:
            extra["samples_xyz_m"] = samples
    else:
        fps = float(tf.fps)
        H = max(1, int(round(horizon_s * fps)))
        xyz, _ = baseline_preview(np.asarray(tf.xyz_m, np.float64), fps, H, kind)
        t_s, name, stochastic, names = np.arange(1, H + 1) / fps, kind, False, np.asarray(tf.joint_names)
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
            "joint_names": names,
            "stochastic": np.bool_(stochastic),
            **extra,
        },
    )
    return out_path
