"""The one writer of ``samples_<model>.npz`` (``forecast eval --save-samples``), for every protocol that
saves its forecasts (cmu, cmu8, hik), so that anyone can rescore a run with any metric.

Keys: ``pred (N,S,T,J,3)``, ``obs (N,T_obs,J,3)``, ``gt (N,T,J,3)`` in metres, ``fps``, ``joint_names``,
``activity (N,)``, ``clip (N,)`` (the clip each window comes from: leave the query's own clip out of an
NDMS database, as the seed does), ``model``, and what a protocol adds (cmu8: ``protocol``,
``protocol_mm_per_m``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from roomcap.core.errors import InputError
from roomcap.core.fileio import atomic_path


def samples_path(out_dir: str | os.PathLike, model: str) -> Path:
    """``<out_dir>/samples_<model>.npz``, the model's name as a file name (``@``: ``_at_``, ``/``: ``_``)."""
    return Path(out_dir) / f"samples_{model.replace('@', '_at_').replace('/', '_')}.npz"


def write_samples(
    out_dir: str | os.PathLike, model: str, pred, obs, gt, fps: float, joint_names, activity, clip, **extra
) -> Path:
    """Write one model's forecasts of N windows as :func:`samples_path` (atomically) -> its path.
    ``activity`` and ``clip``: one string per window; ``extra``: further arrays of the protocol."""
    pred, obs, gt = (np.asarray(a, np.float32) for a in (pred, obs, gt))
    activity, clip = np.array([str(a) for a in activity]), np.array([str(c) for c in clip])
    n = len(pred)
    if not (len(obs) == len(gt) == len(activity) == len(clip) == n):
        raise InputError(
            f"samples of {model}: {n} forecasts but {len(obs)} observations, {len(gt)} truths, "
            f"{len(activity)} activities and {len(clip)} clips"
        )
    path = samples_path(out_dir, model)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        np.savez_compressed(
            tmp,
            pred=pred,
            obs=obs,
            gt=gt,
            fps=np.float64(fps),
            joint_names=np.array(list(joint_names)),
            activity=activity,
            clip=clip,
            model=np.array(model),
            **extra,
        )
    return path
