"""Forecast checkpoints: writing, reading and building models from them, and the baselines.

Checkpoints (``torch.save`` of plain containers, loaded with ``weights_only=True``) carry
``schema = "forecast-checkpoint/1"``, the model kind, its config, the skeleton id and joint names, the
frame rate and the normalisation convention, plus the state dict (k-means centres, feature statistics
and the diffusion schedule are buffers inside it).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from scipy.cluster.vq import kmeans2

from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import atomic_path
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.runtime.config import BASELINES
from roomcap.forecast.runtime.models import (
    ConstantVelocity,
    FoolClusters,
    SlideLastPose,
    ZeroVelocity,
)
from roomcap.forecast.runtime.predict import LHIP, RHIP
from roomcap.forecast.runtime.registry import DISCRIMINATOR_PREFIXES, MODELS, build_model, config_from_dict
from roomcap.keypoints.skeletons import get_skeleton

CKPT_SCHEMA = "forecast-checkpoint/1"
NORMALISATION = "eq. 3.8 at the last observed frame: root = mid-hips, hip vector (left->right) on +x, z up"


def write_checkpoint(
    path: str | os.PathLike,
    schema: str,
    kind: str,
    *,
    config,
    skeleton: str,
    fps: float,
    normalisation: str,
    extra: dict | None,
    **payload,
) -> None:
    """Write a forecast checkpoint atomically: its config, skeleton, joints, fps and normalisation, then the
    caller's ``payload`` (weights and whatever else the model needs)."""
    blob = {
        "schema": schema,
        "kind": kind,
        "config": dataclasses.asdict(config),
        "skeleton": skeleton,
        "joint_names": list(get_skeleton(skeleton).joint_names),
        "fps": float(fps),
        "normalisation": normalisation,
        **payload,
        "extra": extra or {},
    }
    with atomic_path(path) as tmp:
        torch.save(blob, tmp)


# Every checkpoint schema of the project (forecast/checkpoints), for a message that names what a file is
# when a reader gets one it does not read: schema -> (what it is, what reads it). The behaviour and
# characteristic modules own their constants; tests/test_forecast_models.py checks that these match them.
KNOWN_SCHEMAS = {
    CKPT_SCHEMA: (
        "a forecast checkpoint (GRU, intention or Social Diffusion)",
        "`forecast sample --checkpoint PATH` and `forecast eval --checkpoints PATH` read it",
    ),
    "forecast-characteristic/1": (
        "a characteristic-3D-pose checkpoint (Diller ch. 3)",
        "`forecast characteristic eval --checkpoint PATH` reads it",
    ),
    "forecast-cmu8-checkpoint/1": (
        "a DCT + MLP of the CMU 8-action benchmark (its own 3D points at 60 Hz, not tracks)",
        "`forecast eval --protocol cmu8 --checkpoints PATH` scores it",
    ),
    "behaviour_checkpoint/1": (
        "a behaviour model (next actions and their poses, Diller ch. 4)",
        "`forecast behaviour sample|eval --checkpoint PATH` reads it",
    ),
    "behaviour_quality/1": (
        "a behaviour pose-quality model (Diller ch. 4)",
        "`forecast behaviour` reads it beside its behaviour model",
    ),
}


def describe_checkpoint(blob) -> str:
    """What a loaded checkpoint ``blob`` is, in words: one of :data:`KNOWN_SCHEMAS`, another version of one
    (``name/N``), a bare state dict, or whatever else it holds."""
    if not isinstance(blob, dict):
        return f"a {type(blob).__name__}, not a checkpoint dict"
    schema = blob.get("schema")
    if schema in KNOWN_SCHEMAS:
        what, how = KNOWN_SCHEMAS[schema]
        kind = f" ('{blob['kind']}')" if isinstance(blob.get("kind"), str) else ""
        return f"{what}{kind}: {how}"
    if isinstance(schema, str):
        name, _, version = schema.rpartition("/")
        ours = [k for k in KNOWN_SCHEMAS if k.rpartition("/")[0] == name]
        if ours:
            what, _ = KNOWN_SCHEMAS[ours[0]]
            return (
                f"{what} of schema '{schema}', written by another roomcap version (this one reads "
                f"'{ours[0]}'): forecast with the version that wrote it, or retrain it with this one"
            )
        return f"a checkpoint of schema '{schema}', which roomcap does not know"
    if blob and all(isinstance(v, torch.Tensor) for v in blob.values()):
        return (
            f"a bare PyTorch state dict ({len(blob)} tensors, no schema, config or skeleton), so the model "
            "cannot be rebuilt from it: save the model with "
            "roomcap.forecast.runtime.checkpoint.save_checkpoint(model, kind, config), or retrain it"
        )
    return f"a dict without a schema (keys {sorted(map(str, blob))[:6]})"


def read_checkpoint(
    path: Path,
    schema: str,
    skeleton: str | None,
    what: str,
    train_cmd: str,
    map_location: str = "cpu",
    missing_as_is: bool = False,
) -> dict:
    """Load a checkpoint written by :func:`write_checkpoint` (weights_only=True) and check that it is one
    (``schema``) and fits the caller's data ``skeleton`` (None: any); errors say how to get a good one.
    ``missing_as_is``: a missing file raises FileNotFoundError, for a caller that words that case itself."""
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - re-raised with what to do
        if missing_as_is and isinstance(e, FileNotFoundError):
            raise
        raise FormatError(
            path, None, f"not a readable {what} ({type(e).__name__}: {e}).", f"Train one with `{train_cmd}`."
        ) from e
    if not isinstance(blob, dict) or blob.get("schema") != schema:
        got = blob.get("schema") if isinstance(blob, dict) else type(blob).__name__
        raise FormatError(
            path,
            "schema",
            f"expected '{schema}', got {got!r}: this is {describe_checkpoint(blob)}.",
            f"A {what} of this version comes from `{train_cmd}`.",
        )
    if skeleton is not None and blob["skeleton"] != skeleton:
        raise FormatError(
            path,
            "skeleton",
            f"the checkpoint was trained on skeleton '{blob['skeleton']}' "
            f"({len(blob['joint_names'])} joints) but the data is '{skeleton}'.",
            f"Convert the data to '{blob['skeleton']}' or train a model on '{skeleton}'.",
        )
    return blob


def save_checkpoint(
    path: str | os.PathLike,
    model: torch.nn.Module,
    kind: str,
    config,
    skeleton: str = "body19",
    fps: float = fdata.TARGET_FPS,
    extra: dict | None = None,
) -> None:
    state = {
        k: v.detach().cpu()
        for k, v in model.state_dict().items()
        if not k.startswith(DISCRIMINATOR_PREFIXES)  # only needed for training; keeps files < 2 MB
    }
    write_checkpoint(
        path,
        CKPT_SCHEMA,
        kind,
        config=config,
        skeleton=skeleton,
        fps=fps,
        normalisation=NORMALISATION,
        extra=extra,
        state_dict=state,
    )


def load_checkpoint(path: str | os.PathLike, skeleton: str | None = None, map_location: str = "cpu"):
    """-> (model, meta). ``skeleton``: the skeleton the caller's data uses; a mismatch is a clear error."""
    blob = read_checkpoint(
        Path(path), CKPT_SCHEMA, skeleton, "forecast checkpoint", "forecast train", map_location
    )
    kind = blob.get("kind")
    if kind not in MODELS:
        raise FormatError(
            path,
            "kind",
            f"a '{kind}' model, which this roomcap version does not build (it builds {', '.join(MODELS)}).",
            "Forecast with the roomcap version that wrote it, or train one of these: "
            f"`forecast train --model {'|'.join(MODELS)}`.",
        )
    try:
        config = config_from_dict(kind, blob["config"])
    except (InputError, FormatError) as e:
        why = str(e).removeprefix(f"<input>: field '{kind} config': ").removesuffix(" Remove or rename them.")
        raise FormatError(
            path,
            "config",
            f"its {kind} config does not fit this roomcap version ({why.rstrip('.')}).",
            f"It was written by another version: forecast with that one, or retrain with `forecast train "
            f"--model {kind}` (--set the keys above that this version knows).",
        ) from None
    model = build_model(kind, config, len(blob["joint_names"]), blob["state_dict"])
    meta = {k: v for k, v in blob.items() if k != "state_dict"}
    meta["config"] = config
    return model.to(map_location), meta


def baseline(kind: str, lhip: int = LHIP, rhip: int = RHIP) -> torch.nn.Module:
    if kind in ("zero_velocity", "zero"):
        return ZeroVelocity()
    if kind in ("constant_velocity", "const"):
        return ConstantVelocity()
    if kind == "slide":
        return SlideLastPose(lhip, rhip)
    raise InputError(f"unknown baseline '{kind}'; baselines: {BASELINES}")


def fool_model(train_windows: fdata.WindowSet, k: int = 48, seed: int = 0) -> FoolClusters:
    """Sec. 6.4.4's fool: 48 cluster means of the training poses (hip-centric, per-frame normalised)."""
    x = train_windows.x[:, :, 0].reshape(-1, train_windows.x.shape[3], 3)
    R, root = fdata.norm_frame(x, LHIP, RHIP)
    loc = np.einsum("nij,nkj->nki", R, x - root[:, None]).reshape(len(x), -1)
    rng = np.random.default_rng(seed)
    sub = loc[rng.choice(len(loc), min(len(loc), 20000), replace=False)].astype(np.float64)
    with warnings.catch_warnings():  # tiny data sets leave clusters empty; the centres are still poses
        warnings.simplefilter("ignore")
        centres, _ = kmeans2(sub, k, minit="++", seed=seed)
    centres = centres[np.isfinite(centres).all(1)]
    return FoolClusters(torch.from_numpy(centres.astype(np.float32)))
